"""Flax models: detection encoders, the LSTM trunk, and the assembled NavModel."""

from orgnav_jax.models.navmodel import (
    ENCODERS, ModelInputs, NavCarry, NavModel, build_model, check_feature_widths,
    feature_widths, init_params, model_inputs, previous_action)
from orgnav_jax.models.trunk import Trunk, dropout_mask, reset_carry

__all__ = ["ENCODERS", "ModelInputs", "NavCarry", "NavModel", "Trunk", "build_model",
           "check_feature_widths", "dropout_mask", "feature_widths", "init_params",
           "model_inputs", "previous_action", "reset_carry"]
