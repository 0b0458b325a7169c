#!/usr/bin/env bash
# A real single-node SLURM cluster on this machine, for tests and for trying the SLURM launcher:
#   scripts/local-slurm.sh start    install slurm-wlm + munge (Debian/Ubuntu, as root) if missing,
#                                   write /etc/slurm/slurm.conf, start munged, slurmctld, slurmd
#   scripts/local-slurm.sh status   sinfo + squeue; exit 1 when the cluster does not answer
#   scripts/local-slurm.sh stop     stop slurmd, slurmctld and munged (the ones this script started)
# One node (this host, its CPUs and memory), one partition "debug" (the default), no accounting
# (sacct fails; submitit only warns). Daemons run as root: proctrack/linuxproc, task/none, so no
# cgroups are needed (works in containers). State, pid files and logs live under $STATE_DIR.
set -euo pipefail

STATE_DIR=${RLEXP_SLURM_DIR:-/var/lib/rlexp-slurm}
CONF=/etc/slurm/slurm.conf
MARK="# rlexp local-slurm.sh"
PARTITION=${RLEXP_SLURM_PARTITION:-debug}

die() { echo "local-slurm: $*" >&2; exit 1; }
log() { echo "local-slurm: $*"; }

need_root() {
    [[ $(id -u) -eq 0 ]] || die "run as root (it installs packages and starts system daemons)"
}

install_packages() {
    if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null \
        && command -v sbatch >/dev/null; then
        return
    fi
    command -v apt-get >/dev/null || die "slurm-wlm/munge missing and no apt-get: install them yourself"
    log "installing slurm-wlm and munge (apt-get)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq slurm-wlm munge >/dev/null
}

pid_alive() {  # pid_alive PIDFILE -> true when the pid in it is a live process
    [[ -s $1 ]] && kill -0 "$(cat "$1")" 2>/dev/null
}

write_conf() {
    local host cpus mem
    host=$(hostname)
    cpus=$(nproc)
    # slurmd -C reports what slurmd will detect; configuring more memory than that drains the node.
    mem=$(slurmd -C 2>/dev/null | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' | head -1)
    [[ -n $mem ]] || mem=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 ))
    mem=$(( mem * 95 / 100 ))
    if [[ -f $CONF ]] && ! grep -q "^$MARK" "$CONF"; then
        die "$CONF exists and was not written by this script; move it away first"
    fi
    mkdir -p /etc/slurm "$STATE_DIR"/{ctld,d,log}
    cat >"$CONF" <<EOF
$MARK (single-node test cluster; regenerated on every start)
ClusterName=rlexp-local
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
DefMemPerCPU=$(( mem / cpus ))
SchedulerType=sched/backfill
ReturnToService=2
JobRequeue=1
MinJobAge=600
KillWait=30
SlurmctldTimeout=30
SlurmdTimeout=60
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
StateSaveLocation=$STATE_DIR/ctld
SlurmdSpoolDir=$STATE_DIR/d
SlurmctldPidFile=$STATE_DIR/slurmctld.pid
SlurmdPidFile=$STATE_DIR/slurmd.pid
SlurmctldLogFile=$STATE_DIR/log/slurmctld.log
SlurmdLogFile=$STATE_DIR/log/slurmd.log
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=$PARTITION Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
    log "wrote $CONF (node $host: $cpus CPUs, ${mem} MB; partition $PARTITION)"
}

start_munge() {
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge 2>/dev/null || true
    if [[ ! -s /etc/munge/munge.key ]]; then
        mkdir -p /etc/munge
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
        chown munge:munge /etc/munge/munge.key
        chmod 400 /etc/munge/munge.key
    fi
    if pid_alive /run/munge/munged.pid && munge -n </dev/null | unmunge >/dev/null 2>&1; then
        return
    fi
    log "starting munged"
    runuser -u munge -- /usr/sbin/munged --force
    for _ in $(seq 50); do
        munge -n </dev/null | unmunge >/dev/null 2>&1 && return
        sleep 0.1
    done
    die "munged does not answer (see /var/log/munge/munged.log)"
}

node_state() {
    { sinfo -h -N -o "%T" 2>/dev/null || true; } | head -1
}

start() {
    need_root
    install_packages
    if pid_alive "$STATE_DIR/slurmctld.pid" && pid_alive "$STATE_DIR/slurmd.pid" && sinfo >/dev/null 2>&1; then
        log "already running"
        status
        return
    fi
    write_conf
    start_munge
    if ! pid_alive "$STATE_DIR/slurmctld.pid"; then
        log "starting slurmctld (fresh state: no jobs from an earlier start)"
        /usr/sbin/slurmctld -c
    fi
    if ! pid_alive "$STATE_DIR/slurmd.pid"; then
        log "starting slurmd"
        /usr/sbin/slurmd
    fi
    local state=""
    for _ in $(seq 60); do
        state=$(node_state)
        case $state in
            idle*|mixed*|allocated*) break ;;
            down*|drain*) scontrol update NodeName="$(hostname)" State=RESUME 2>/dev/null || true ;;
        esac
        sleep 1
    done
    case $state in
        idle*|mixed*|allocated*) log "up: node $(hostname) is $state" ;;
        *) die "node state '$state' after 60 s; see $STATE_DIR/log/slurmctld.log and slurmd.log" ;;
    esac
}

stop() {
    need_root
    local f jobs
    # End this cluster's jobs first: a job whose slurmd goes away mid-run leaves its slurmstepd/srun
    # behind, and they would hold the node after the next start.
    jobs=$(squeue -h -o %i 2>/dev/null || true)
    if [[ -n $jobs ]]; then
        log "cancelling jobs: $(echo $jobs)"
        scancel $jobs 2>/dev/null || true
        for _ in $(seq 50); do [[ -z $(squeue -h -o %i 2>/dev/null) ]] && break; sleep 0.2; done
    fi
    for f in slurmd slurmctld; do
        if pid_alive "$STATE_DIR/$f.pid"; then
            log "stopping $f"
            kill "$(cat "$STATE_DIR/$f.pid")"
        fi
    done
    for f in slurmd slurmctld; do
        for _ in $(seq 50); do pid_alive "$STATE_DIR/$f.pid" || break; sleep 0.2; done
    done
    if pid_alive /run/munge/munged.pid; then
        log "stopping munged"
        kill "$(cat /run/munge/munged.pid)"
    fi
}

status() {
    if ! sinfo >/dev/null 2>&1; then
        echo "local-slurm: not running (sinfo does not answer)"
        return 1
    fi
    sinfo
    squeue
}

case ${1:-} in
    start) start ;;
    stop) stop ;;
    status) status ;;
    restart) stop; start ;;
    *) echo "usage: $0 start|stop|status|restart" >&2; exit 2 ;;
esac
