"""record_video's checks before the run: its parameters taken together, then one frame rendered from
a built env and the mp4 encoder found (what would otherwise fail at the end of the first round);
and the writing of its mp4, checked to be whole (``write_mp4``)."""

from __future__ import annotations

import errno
import logging
import os
import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np

from rlexp.events.env_access import base_env
from rlexp.events.output import check_save_path, write_new_file

log = logging.getLogger(__name__)

#: Frames are held in memory until the round ends: at most this many bytes of them.
MAX_VIDEO_BYTES = 4 * 2**30

#: record_video's parameter defaults (those of ``RecordVideo.__call__`` / ``finalize``).
VIDEO_DEFAULTS: dict[str, Any] = {
    "name": "eval",
    "resolution": (640, 480),
    "eye": None,
    "target": None,
    "up": (0, 0, 1),
    "intrinsics": None,
    "fovy": None,
    "env_id": 0,
    "max_frames": 2000,
    "fps": 25,
}


def check_video_params(params: dict[str, Any], where: str) -> None:
    """Rules across parameters, and whether this process can render offscreen at all."""
    from rlexp.envs.native.render import GL_FIX, gl_problem

    check_save_path(params, where)
    p = {**VIDEO_DEFAULTS, **params}
    if p["intrinsics"] is not None and p["fovy"] is not None:
        raise ValueError(f"{where}.params: give intrinsics or fovy, not both")
    if p["eye"] is not None and p["target"] is not None:
        forward = np.subtract(p["target"], p["eye"], dtype=float)
        dist = float(np.linalg.norm(forward))
        if dist < 1e-9:
            raise ValueError(f"{where}.params: eye={p['eye']} and target are the same point")
        if np.linalg.norm(np.cross(forward / dist, np.asarray(p["up"], float))) < 1e-9:
            raise ValueError(f"{where}.params.up={p['up']} is parallel to target - eye")
    if np.linalg.norm(np.asarray(p["up"], float)) < 1e-9:
        raise ValueError(f"{where}.params.up={p['up']} must not be zero")
    width, height = (int(v) for v in p["resolution"])
    size = int(p["max_frames"]) * width * height * 3
    if size > MAX_VIDEO_BYTES:
        raise ValueError(
            f"{where}.params: max_frames={p['max_frames']} frames of {width}x{height} hold "
            f"{size / 2**30:.1f} GiB in memory (at most {MAX_VIDEO_BYTES // 2**30} GiB); lower "
            "max_frames or resolution"
        )
    # Only a MUJOCO_GL that MuJoCo refuses to import with (no MuJoCo env could run): whether
    # this machine can render is check_env's question, not the config's (rlexp eval reads the
    # config of a run with videos on machines that cannot render).
    problem = gl_problem(rendering=False)
    if problem is not None:
        raise ValueError(f"{where}: cannot render {width}x{height} offscreen: {problem}; {GL_FIX}")


def check_video_env(env: Any, where: str, num_envs: int | None = None, **params: Any) -> None:
    """Render one frame from ``env`` (a throwaway built copy of the eval env: it is reset, as an
    evaluation round does first) with these params, and find the mp4 encoder: what would
    otherwise fail at the end of the first evaluation round."""
    from rlexp.envs.native.render import GL_FIX, gl_problem

    p = {**VIDEO_DEFAULTS, **params}
    if num_envs is not None and p["env_id"] >= num_envs:
        raise ValueError(
            f"{where}.params.env_id={p['env_id']} but the eval env has {num_envs} copies "
            "(env.num_eval_envs)"
        )
    width, height = (int(v) for v in p["resolution"])
    problem = gl_problem()
    if problem is not None:
        raise ValueError(f"{where}: cannot render {width}x{height} offscreen: {problem}; {GL_FIX}")
    base = base_env(env)
    if not hasattr(base, "render"):
        raise TypeError(f"{where}: {type(base).__name__} cannot render frames")
    try:
        base.reset()
        frame = base.render(
            env_id=0,
            width=width,
            height=height,
            eye=p["eye"],
            target=p["target"],
            up=p["up"],
            intrinsics=p["intrinsics"],
            fovy=p["fovy"],
        )
    except Exception as exc:  # GL failures come as RuntimeError, FatalError, AttributeError...
        text = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc).strip()
        text = (text.splitlines() or [type(exc).__name__])[0].removeprefix("render: ")
        raise ValueError(f"{where}: cannot render {width}x{height} offscreen: {text}") from None
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[-1] != 3:
        raise ValueError(f"{where}: the env renders frames of shape {frame.shape}, not (H, W, 3)")
    if frame.shape[:2] != (height, width):
        log.warning(
            "%s: the env renders %dx%d frames with its own camera (Gymnasium: env.kwargs.width / "
            "height); resolution and the camera params apply to the native tasks",
            where, frame.shape[1], frame.shape[0],
        )  # fmt: skip
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except ImportError:  # the video extra is not installed: one line naming it
        from rlexp.extras import install_hint

        raise ValueError(
            f"{where} needs rlexp's optional 'video' extra (imageio_ffmpeg is not installed): "
            f"{install_hint('video')}"
        ) from None
    except Exception as exc:  # RuntimeError when no ffmpeg binary is found
        raise ValueError(f"{where}: cannot write mp4 videos: {exc}") from None


#: Free bytes below which an mp4 that came out incomplete is put down to a full disk.
FULL_DISK_BYTES = 1 << 20


def write_mp4(path: Path, frames: list[np.ndarray], fps: float) -> None:
    """Encode ``frames`` into ``path`` (through a temporary file renamed over it); ``OSError``
    naming the file and why when it cannot be written whole. The encoder is an ffmpeg process
    whose failures (a full disk, a quota) imageio does not report: the file it leaves is checked to
    be a complete mp4 before it takes the final name."""
    import imageio.v2 as imageio

    def write(tmp: Path) -> None:
        with imageio.get_writer(
            tmp, fps=fps, codec="libx264", macro_block_size=1, ffmpeg_log_level="quiet"
        ) as writer:  # quiet: ffmpeg's own lines would go around the log; the check below speaks
            for frame in frames:
                writer.append_data(frame)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)  # a write the filesystem deferred fails here, not after the rename
        finally:
            os.close(fd)
        problem = mp4_problem(tmp)
        if problem is not None:
            if shutil.disk_usage(tmp.parent).free < FULL_DISK_BYTES:
                raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({problem})", str(path))
            raise OSError(errno.EIO, f"the encoder left an incomplete file ({problem})", str(path))

    write_new_file(path, write)


def mp4_problem(path: Path) -> str | None:
    """Why ``path`` is not a whole mp4 (its top-level boxes must cover the file exactly and hold
    ``ftyp``, ``mdat`` and ``moov``, which ffmpeg writes last), or None."""
    size = path.stat().st_size
    seen: set[bytes] = set()
    pos = 0
    with open(path, "rb") as f:
        while pos < size:
            f.seek(pos)
            head = f.read(8)
            if len(head) < 8:
                return f"{size} bytes end inside a box header"
            length, kind = struct.unpack(">I4s", head)
            if length == 1:  # a 64-bit size follows
                big = f.read(8)
                length = struct.unpack(">Q", big)[0] if len(big) == 8 else 0
            elif length == 0:  # "to the end of the file": a box whose size was never filled in
                length = size - pos
            if length < 8 or pos + length > size:
                return f"the {kind.decode(errors='replace')!r} box is cut short at {size} bytes"
            seen.add(kind)
            pos += length
    missing = [k.decode() for k in (b"ftyp", b"mdat", b"moov") if k not in seen]
    return f"no {', '.join(missing)} box in {size} bytes" if missing else None
