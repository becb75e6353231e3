"""The driving policy as an sb3-contrib recurrent policy, with a fused recurrent pass.

Differences from sb3-contrib's `CnnLstmPolicy` (each measured in benchmarks/bench_train_speed.py):
- a small CNN (`ImageEncoder`) instead of NatureCNN, and one LSTM shared by the steering and value heads, with no
  critic LSTM; the value loss trains the shared trunk too (CleanRL's ppo_atari_lstm does the same);
- `_process_sequence` runs the LSTM as one fused call per piece between episode starts (`run_lstm`), where
  sb3-contrib loops over every time step in Python as soon as a minibatch holds one episode start.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from sb3_contrib.common.recurrent.type_aliases import RNNStates
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from drivesim.policy.net import DrivingNet, ImageEncoder, run_lstm


class EncoderExtractor(BaseFeaturesExtractor):
    """SB3 features extractor around `ImageEncoder` (standardization inside, so images stay uint8 until here)."""

    def __init__(
        self, observation_space: spaces.Box, conv_layers: list, features_dim: int = 128, input_pool: int = 1
    ) -> None:
        super().__init__(observation_space, features_dim)
        self.encoder = ImageEncoder(observation_space.shape, conv_layers, features_dim, input_pool)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) 0..255 -> (N, features_dim)."""
        return self.encoder(observations)


def _conv_layers(conv_layers: list | None) -> list[list[int]]:
    """The convolutions exactly as given (the architecture recorded is the one built); at least one is needed."""
    layers = [list(map(int, layer)) for layer in conv_layers or []]
    if not layers or any(len(layer) != 3 or min(layer) < 1 for layer in layers):
        raise ValueError(
            f"conv_layers {conv_layers!r}: give at least one (out_channels, kernel_px, stride_px), each >= 1"
        )
    return layers


class DrivingLstmPolicy(RecurrentActorCriticPolicy):
    """Small CNN -> one shared LSTM -> Gaussian steering and value; for `RecurrentPPO`.

    :param observation_space: Box (C, H, W) uint8.
    :param action_space: Box (1,) in [-1, 1].
    :param lr_schedule: learning rate schedule.
    :param conv_layers: (out_channels, kernel, stride) per convolution.
    :param features_dim: CNN output size.
    :param input_pool: average-pool factor before the convolutions.
    :param lstm_hidden_size: LSTM cells.
    :param n_lstm_layers: LSTM layers.
    :param log_std_init: initial log std of the steering distribution.
    :param memory_outputs: outputs of a linear head on the LSTM that the cloning passes fit to where the other car is
        (`clone_outputs`; 0: no head). It is not part of the driving net: not exported, not acted on.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Any,
        conv_layers: list | None = None,
        features_dim: int = 128,
        input_pool: int = 1,
        lstm_hidden_size: int = 128,
        n_lstm_layers: int = 1,
        log_std_init: float = -1.0,
        memory_outputs: int = 0,
        **kwargs: Any,
    ) -> None:
        self.arch = {
            "conv_layers": _conv_layers(conv_layers),
            "features_dim": int(features_dim),
            "input_pool": int(input_pool),
            "lstm_hidden_size": int(lstm_hidden_size),
            "lstm_layers": int(n_lstm_layers),
            "log_std_init": float(log_std_init),
        }
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=[],
            activation_fn=nn.ReLU,
            log_std_init=log_std_init,
            features_extractor_class=EncoderExtractor,
            features_extractor_kwargs={
                "conv_layers": self.arch["conv_layers"],
                "features_dim": features_dim,
                "input_pool": input_pool,
            },
            share_features_extractor=True,
            normalize_images=False,
            lstm_hidden_size=lstm_hidden_size,
            n_lstm_layers=n_lstm_layers,
            shared_lstm=True,
            enable_critic_lstm=False,
            **kwargs,
        )
        # Made after the optimizer PPO builds in super().__init__: only the cloning passes train the head.
        self.memory_net = nn.Linear(lstm_hidden_size, memory_outputs) if memory_outputs > 0 else None

    @staticmethod
    def _process_sequence(
        features: torch.Tensor,
        lstm_states: tuple[torch.Tensor, torch.Tensor],
        episode_starts: torch.Tensor,
        lstm: nn.LSTM,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        # Same layout as sb3-contrib: features are (n_seq * T, F) sequence-major.
        n_seq = lstm_states[0].shape[1]
        sequence = features.reshape((n_seq, -1, lstm.input_size)).swapaxes(0, 1)
        starts = episode_starts.reshape((n_seq, -1)).swapaxes(0, 1)
        output, states = run_lstm(lstm, sequence, lstm_states, starts)
        return torch.flatten(output.transpose(0, 1), start_dim=0, end_dim=1), states

    observations_preprocessed = False
    """Set by ChunkedRecurrentPPO.train while the buffer hands out `preprocess_observations`' output."""

    def preprocess_observations(self, observations: np.ndarray, batch: int = 1024) -> np.ndarray:
        """The encoder's parameter-free preprocessing of (..., C, H, W) uint8 images, done once per update rather
        than once per epoch (it is a third of a training pass)."""
        encoder = self.features_extractor.encoder
        flat = observations.reshape(-1, *observations.shape[-3:])
        with torch.no_grad():
            parts = [
                encoder.preprocess(torch.from_numpy(flat[i : i + batch]).to(self.device)).cpu().numpy()
                for i in range(0, len(flat), batch)
            ]
        out = np.concatenate(parts)
        return out.reshape(*observations.shape[:-3], *out.shape[1:])

    def evaluate_actions(
        self, obs: torch.Tensor, actions: torch.Tensor, lstm_states: RNNStates, episode_starts: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Values, log-probabilities of `actions` and entropies over sequences; the value loss reaches the trunk."""
        if self.observations_preprocessed:
            features = self.features_extractor.encoder.encode_preprocessed(obs)
        else:
            features = self.extract_features(obs)
        latent, _ = self._process_sequence(features, lstm_states.pi, episode_starts, self.lstm_actor)
        distribution = self._get_action_dist_from_latent(latent)
        return self.value_net(latent), distribution.log_prob(actions), distribution.entropy()

    def clone_outputs(
        self, obs: torch.Tensor, actions: torch.Tensor, lstm_states: RNNStates, episode_starts: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Log-probabilities of `actions` over sequences and the memory head's prediction at each step (None without
        a head): what the cloning passes fit."""
        features = self.extract_features(obs)
        latent, _ = self._process_sequence(features, lstm_states.pi, episode_starts, self.lstm_actor)
        log_prob = self._get_action_dist_from_latent(latent).log_prob(actions)
        return log_prob, (self.memory_net(latent) if self.memory_net is not None else None)

    def driving_net_state(self) -> dict[str, torch.Tensor]:
        """The weights under `DrivingNet`'s names (what a run folder's policy.pt holds)."""
        out: dict[str, torch.Tensor] = {}
        for name, tensor in self.state_dict().items():
            for ours, theirs in _NAME_MAP:
                if name.startswith(theirs):
                    out[ours + name[len(theirs) :]] = tensor.detach().clone()
                    break
        return out

    def load_driving_net_state(self, state: dict[str, torch.Tensor]) -> None:
        """Load weights saved by `driving_net_state` (warm start, resume)."""
        own = self.state_dict()
        for name, tensor in state.items():
            for ours, theirs in _NAME_MAP:
                if name.startswith(ours):
                    own[theirs + name[len(ours) :]].copy_(tensor)
                    break

    def to_driving_net(self) -> DrivingNet:
        """A plain `DrivingNet` with this policy's weights."""
        net = DrivingNet(
            self.observation_space.shape,
            self.arch["conv_layers"],
            self.arch["features_dim"],
            self.arch["lstm_hidden_size"],
            self.arch["lstm_layers"],
            self.arch["input_pool"],
            self.arch["log_std_init"],
        )
        net.load_state_dict(self.driving_net_state())
        return net


# (DrivingNet name prefix, sb3 policy name prefix); the pi/vf extractor aliases are skipped (same tensors).
_NAME_MAP = (
    ("encoder.", "features_extractor.encoder."),
    ("lstm.", "lstm_actor."),
    ("action_head.", "action_net."),
    ("value_head.", "value_net."),
    ("log_std", "log_std"),
)
