"""Layer 2, policies: the Gaussian actor-critic (``actor_critic``), its heads (``heads``), the fast
numpy sampler (``numpy_sampler``), what each network reads of the observation (``inputs``) and the
CNN image encoders (``encoders``); the recurrent actor-critic (``memory``, registered in
``actor_critic.RECURRENT``) and SAC's and TD3's actors and Q networks (``offpolicy``, which registers
``policy.name=sac`` / ``td3`` in ``actor_critic.POLICIES``), imported here so that they are
registered wherever a policy is built.

May import: layers 0-1 and the other pieces.
"""

from rlexp.policies import (
    memory,  # noqa: E402,F401  (registers the recurrent policies)
    offpolicy,  # noqa: E402, F401  (registers policy=sac / policy=td3)
)
