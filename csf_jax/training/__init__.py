"""The offline stage: PF prior-ensemble datasets, conditional score matching, orbax checkpoints."""

from csf_jax.training.data import Dataset, DatasetConfig, generate, load
from csf_jax.training.fit import train_prior
from csf_jax.training.train import TrainConfig, TrainState, train

__all__ = ["Dataset", "DatasetConfig", "TrainConfig", "TrainState", "generate", "load", "train",
           "train_prior"]
