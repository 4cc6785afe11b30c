"""Stage 1: A2C (+ IL) training of the navigation model (docs/training.md).

config (TrainConfig), rollout, losses, update (the jitted chunk), driver (the host loop
both stages share), loop (stage 1 on the driver), run_dir, checkpoints, runs (a saved
run's scenes, model and policy), memory (the pre-check estimate), scale (device mesh,
processes). The library entry point is orgnav_jax.api.train.
"""
