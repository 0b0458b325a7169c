"""Layer 2, policies: the Gaussian actor-critic (``actor_critic``), its heads (``heads``), the fast
numpy sampler (``numpy_sampler``), what each network reads of the observation (``inputs``) and the
CNN image encoders (``encoders``), and the recurrent actor-critic (``memory``), imported here so
that it is registered wherever a policy is built (``actor_critic.RECURRENT``).

May import: layers 0-1 and the other pieces.
"""

from rlexp.policies import memory  # noqa: E402,F401  (registers the recurrent policies)
