"""Flax models: detection encoders, the LSTM trunk, and the assembled NavModel."""

from orgnav_jax.models.navmodel import (
    ENCODERS, ModelInputs, NavModel, build_model, init_params, model_inputs)
from orgnav_jax.models.trunk import Trunk, dropout_mask, reset_carry

__all__ = ["ENCODERS", "ModelInputs", "NavModel", "Trunk", "build_model", "dropout_mask", "init_params",
           "model_inputs", "reset_carry"]
