"""PPO hyperparameters (rsl-rl's names) and the network; ``to_rsl_rl`` is the only place emitting class names."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from spiral.config.base import NonNegFloat, PosFloat, PosInt, StrictModel

__all__ = ["PPOCfg"]


class PPOCfg(StrictModel):
    """rsl-rl PPO settings, actor-critic sizes and checkpointing; the defaults are the shipped recipe's."""

    num_steps_per_env: PosInt = Field(default=24, description="Rollout length per iteration")
    num_learning_epochs: PosInt = Field(default=5)
    num_mini_batches: PosInt = Field(default=4)
    clip_param: PosFloat = Field(default=0.2)
    gamma: float = Field(default=0.99, gt=0, le=1)
    lam: float = Field(default=0.95, gt=0, le=1)
    value_loss_coef: NonNegFloat = Field(default=1.0)
    entropy_coef: NonNegFloat = Field(default=0.0, description="Weight of the entropy bonus (pipelines/paper.yaml: "
                                      "0.005)")
    learning_rate: PosFloat = Field(default=1.0e-3)
    max_grad_norm: PosFloat = Field(default=1.0)
    schedule: Literal["adaptive", "fixed"] = Field(default="adaptive")
    desired_kl: PosFloat = Field(default=0.01)
    actor_hidden_dims: list[PosInt] = Field(default=[128, 128], min_length=1)
    critic_hidden_dims: list[PosInt] = Field(default=[128, 128], min_length=1)
    activation: Literal["elu", "relu", "tanh", "selu", "lrelu"] = Field(default="elu")
    init_noise_std: PosFloat = Field(default=0.5, description="Initial action noise (actions span [−1, 1])")
    min_noise_std: PosFloat = Field(default=0.05, description="Lower clamp of the action noise")
    max_noise_std: PosFloat = Field(
        default=10.0, description="Upper clamp of the action noise, also of the noise a stage takes over from its init"
    )
    bound_loss_coef: NonNegFloat = Field(
        default=0.5,
        description="Weight of a loss on the actor's mean actions beyond the action range (mean over samples of the "
        "summed squared excess over ±1): keeps the exploration noise on both sides of the mean where the env "
        "would clamp every sample alike (e.g. always full tilt forward, never a sample that brakes); 0: off",
    )
    obs_normalization: bool = Field(default=True)
    mixed_precision: bool = Field(
        default=False,
        description="bfloat16 autocast in the update's forward pass and losses (rsl-rl's use_mixed_precision); "
                    "the rollout, the weights and the optimizer stay float32. Fast on CPUs with AVX512-BF16 or AMX "
                    "and on CUDA GPUs from Ampere on",
    )
    save_interval: PosInt = Field(default=50, description="Iterations between periodic checkpoints")

    @model_validator(mode="after")
    def _noise_range(self) -> PPOCfg:
        if self.min_noise_std > self.max_noise_std:
            raise ValueError(f"min_noise_std {self.min_noise_std} is above max_noise_std {self.max_noise_std}")
        return self

    def to_rsl_rl(self) -> dict:
        """The ``train_cfg`` dictionary of rsl-rl's ``OnPolicyRunner``."""
        return {
            "num_steps_per_env": self.num_steps_per_env,
            "save_interval": self.save_interval,
            "obs_groups": {"actor": ["policy"], "critic": ["critic"]},
            "actor": {**self._model(self.actor_hidden_dims), "distribution_cfg": self._distribution()},
            "critic": self._model(self.critic_hidden_dims),
            "algorithm": self._algorithm(),
        }

    def _model(self, hidden: list[int]) -> dict:
        """rsl-rl's MLP of ``hidden`` layers, with this config's activation and observation normaliser."""
        return {
            "class_name": "rsl_rl.models.MLPModel",
            "hidden_dims": list(hidden),
            "activation": self.activation,
            "obs_normalization": self.obs_normalization,
        }

    def _distribution(self) -> dict:
        """The actor's Gaussian action noise."""
        cfg: dict = {
            "class_name": "rsl_rl.modules.distribution.GaussianDistribution",
            "init_std": self.init_noise_std,
            "std_range": (self.min_noise_std, self.max_noise_std),
        }
        if self.bound_loss_coef > 0:  # the same Gaussian, its mean's gradient with the bound loss's
            cfg.update(class_name="spiral.train.distribution:BoundedGaussianDistribution",
                       bound_coef=self.bound_loss_coef)
        return cfg

    def _algorithm(self) -> dict:
        """rsl-rl's PPO with these hyperparameters, its mini-batches gathered once per update
        (:class:`spiral.train.batches.GatherOncePPO`)."""
        return {
            "class_name": "spiral.train.batches:GatherOncePPO",
            "num_learning_epochs": self.num_learning_epochs,
            "num_mini_batches": self.num_mini_batches,
            "clip_param": self.clip_param,
            "gamma": self.gamma,
            "lam": self.lam,
            "value_loss_coef": self.value_loss_coef,
            "entropy_coef": self.entropy_coef,
            "learning_rate": self.learning_rate,
            "max_grad_norm": self.max_grad_norm,
            "schedule": self.schedule,
            "desired_kl": self.desired_kl,
            "use_mixed_precision": self.mixed_precision,
        }
