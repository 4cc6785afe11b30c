"""The tentative policy network's stage 2 and test-time update (the network itself is
orgnav_jax.models.tpn): config, deadlock detection, per-episode fast weights, the
test-time Policy and stage-2 training."""
