"""The tentative policy network (TPN) around a trained navigation model: its config,
the deadlock detectors, stage-2 training (stage2.py), the per-episode fast weights and
the test-time policy (test_time.py). The network itself is orgnav_jax.models.tpn_net."""
