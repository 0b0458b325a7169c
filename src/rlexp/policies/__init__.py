"""Layer 2, policies: the Gaussian actor-critic (``actor_critic``), its heads (``heads``), the fast
numpy sampler (``numpy_sampler``), what each network reads of the observation (``inputs``) and the
CNN image encoders (``encoders``); SAC's and TD3's actors and Q networks (``offpolicy``, which
registers ``policy.name=sac`` / ``td3`` in ``actor_critic.POLICIES`` when this package loads).

May import: layers 0-1 and the other pieces.
"""

from rlexp.policies import offpolicy  # noqa: E402, F401  (registers policy=sac / policy=td3)
