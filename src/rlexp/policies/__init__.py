"""Layer 2, policies: the Gaussian actor-critic (``actor_critic``), its heads (``heads``), the fast
numpy sampler (``numpy_sampler``), what each network reads of the observation (``inputs``) and the
CNN image encoders (``encoders``).

May import: layers 0-1 and the other pieces.
"""
