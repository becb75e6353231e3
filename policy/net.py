"""The driving policy's network in plain torch: image -> standardized -> small CNN -> LSTM -> steering, value.

Shared by training (wrapped for sb3-contrib's RecurrentPPO in `stages/train/sb3_policy.py`), evaluation
(`policy/run_folder.py::LoadedPolicy`) and export (`DrivingNet` is the module that becomes the ONNX graph).
Importing this module imports torch; `policy/run_folder.py` imports it only when a policy is loaded.

Shapes: images (N, 3, H, W) uint8; LSTM state (layers, N, hidden) float32; actions (N, 1) in [-1, 1] (normalized
steering: curvature = action * max_curvature_1pm of the env config).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

STANDARDIZE_EPS = 1e-3
"""Floor of an image's standard deviation (in [0, 1] intensity units) in the per-image standardization."""


def standardize_images(image_u8: torch.Tensor, pool: int = 1) -> torch.Tensor:
    """Per-image standardization (paper §IV-A): each image (average-pooled by `pool` first) to zero mean and unit
    variance over all its pixels; the std is floored at STANDARDIZE_EPS (in [0, 1] intensity units)."""
    x = image_u8.float()
    if pool > 1:
        # Pooling first makes the standardization 4x cheaper (it was half the cost of a training pass).
        x = _average_pool(x, pool)
    # Two passes written out: torch.var_mean took 275 us for 8 pooled 3 x 32 x 80 images on one CPU thread, this 22.
    flat = x.flatten(1)
    mean = flat.mean(dim=1, keepdim=True)
    centred = flat - mean
    var = (centred * centred).sum(dim=1, keepdim=True) / max(flat.shape[1] - 1, 1)  # unbiased, as var_mean
    scale = torch.rsqrt(var.clamp_min((STANDARDIZE_EPS * 255.0) ** 2))
    return (centred * scale).view(x.shape)


def _average_pool(x: torch.Tensor, pool: int) -> torch.Tensor:
    """avg_pool2d(x, pool) (the last rows and columns that do not fill a window dropped) as sums of strided views:
    on the CPU avg_pool2d took 350 us for 8 images of 3 x 64 x 160, this 50; the sums of whole grey levels are exact
    in float32, so both give the same values. It exports to ONNX as slices and adds."""
    h, w = x.shape[-2] - x.shape[-2] % pool, x.shape[-1] - x.shape[-1] % pool
    rows = x[..., 0:h:pool, :w]
    for dy in range(1, pool):
        rows = rows + x[..., dy:h:pool, :w]
    total = rows[..., 0::pool]
    for dx in range(1, pool):
        total = total + rows[..., dx::pool]
    return total / float(pool * pool)


def conv_out_size(size_px: int, kernel: int, stride: int) -> int:
    """Output size of a 'valid' convolution along one axis."""
    return (size_px - kernel) // stride + 1


class ImageEncoder(nn.Module):
    """Average-pool the image (optionally) and standardize it, then a few strided convolutions and one linear layer.

    :param observation_shape: (C, H, W) of the uint8 image.
    :param conv_layers: (out_channels, kernel, stride) per convolution.
    :param features_dim: size of the feature vector fed to the LSTM.
    :param input_pool: average-pool factor applied to the image before standardization (1: none).
    """

    def __init__(
        self,
        observation_shape: Sequence[int],
        conv_layers: Sequence[Sequence[int]],
        features_dim: int,
        input_pool: int = 1,
    ) -> None:
        super().__init__()
        channels, height, width = (int(v) for v in observation_shape)
        self.input_pool = int(input_pool)
        self.features_dim = int(features_dim)
        layers: list[nn.Module] = []
        height, width = height // self.input_pool, width // self.input_pool
        in_ch = channels
        for out_ch, kernel, stride in conv_layers:
            layers += [nn.Conv2d(in_ch, int(out_ch), int(kernel), int(stride)), nn.ReLU()]
            height, width = (
                conv_out_size(height, int(kernel), int(stride)),
                conv_out_size(width, int(kernel), int(stride)),
            )
            if height < 1 or width < 1:
                raise ValueError(f"conv layers {list(conv_layers)} shrink a {observation_shape} image to nothing")
            in_ch = int(out_ch)
        self.conv = nn.Sequential(*layers)
        self.linear = nn.Sequential(nn.Flatten(), nn.Linear(in_ch * height * width, self.features_dim), nn.ReLU())

    def preprocess(self, image_u8: torch.Tensor) -> torch.Tensor:
        """The parameter-free part: (N, C, H, W) uint8 -> pooled, standardized float (N, C, H/pool, W/pool)."""
        return standardize_images(image_u8, self.input_pool)

    def encode_preprocessed(self, x: torch.Tensor) -> torch.Tensor:
        """The learned part, on `preprocess`'s output -> (N, features_dim)."""
        return self.linear(self.conv(x))

    def forward(self, image_u8: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) uint8 (or float 0..255) -> (N, features_dim)."""
        return self.encode_preprocessed(self.preprocess(image_u8))


def encoder_macs(
    observation_shape: Sequence[int], conv_layers: Sequence[Sequence[int]], features_dim: int, input_pool: int = 1
) -> int:
    """Multiply-adds per frame of `ImageEncoder` (convolutions and the linear layer), for speed reports."""
    channels, height, width = (int(v) for v in observation_shape)
    height, width = height // input_pool, width // input_pool
    macs, in_ch = 0, channels
    for out_ch, kernel, stride in conv_layers:
        height, width = conv_out_size(height, kernel, stride), conv_out_size(width, kernel, stride)
        macs += height * width * out_ch * in_ch * kernel * kernel
        in_ch = out_ch
    return macs + in_ch * height * width * features_dim


def run_lstm(
    lstm: nn.LSTM, features: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor], episode_start: torch.Tensor
) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """Run the LSTM over (T, N, F) features, zeroing the state of sequence n before step t where episode_start[t, n].

    Exact and fused: the sequence is cut only at the time steps where some sequence starts an episode, and each
    piece runs as one `nn.LSTM` call (sb3-contrib loops over every time step as soon as one start is present).
    Returns the outputs (T, N, hidden) and the final state.
    """
    steps = features.shape[0]
    keep = 1.0 - episode_start.float()
    h, c = state
    cuts = [0] + [t for t in range(1, steps) if bool(episode_start[t].any())] + [steps]
    outputs = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        mask = keep[a].view(1, -1, 1)
        out, (h, c) = lstm(features[a:b], (h * mask, c * mask))
        outputs.append(out)
    return (outputs[0] if len(outputs) == 1 else torch.cat(outputs, dim=0)), (h, c)


class DrivingNet(nn.Module):
    """The whole policy as one module: encoder, LSTM, steering mean and value heads, log std of the steering.

    Weight names (`encoder.*`, `lstm.*`, `action_head.*`, `value_head.*`, `log_std`) are what a run folder's
    `policy.pt` holds.

    :param observation_shape: (C, H, W) of the uint8 image.
    :param conv_layers: (out_channels, kernel, stride) per convolution.
    :param features_dim: encoder output size.
    :param lstm_hidden_size: LSTM cells per layer.
    :param lstm_layers: LSTM layers.
    :param input_pool: average-pool factor before the convolutions.
    :param log_std_init: initial log standard deviation of the Gaussian steering distribution.
    """

    def __init__(
        self,
        observation_shape: Sequence[int],
        conv_layers: Sequence[Sequence[int]],
        features_dim: int = 128,
        lstm_hidden_size: int = 128,
        lstm_layers: int = 1,
        input_pool: int = 1,
        log_std_init: float = -1.0,
    ) -> None:
        super().__init__()
        self.encoder = ImageEncoder(observation_shape, conv_layers, features_dim, input_pool)
        self.lstm = nn.LSTM(features_dim, lstm_hidden_size, num_layers=lstm_layers)
        self.action_head = nn.Linear(lstm_hidden_size, 1)
        self.value_head = nn.Linear(lstm_hidden_size, 1)
        self.log_std = nn.Parameter(torch.full((1,), float(log_std_init)))
        self.hidden_size = int(lstm_hidden_size)
        self.lstm_layers = int(lstm_layers)

    def initial_state(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero LSTM state for n sequences: (h, c), each (layers, n, hidden)."""
        zeros = torch.zeros(self.lstm_layers, n, self.hidden_size)
        return zeros, zeros.clone()

    def step(
        self, image_u8: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor], episode_start: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """One time step for N sequences: (steering mean (N, 1) unclipped, value (N, 1), new state)."""
        features = self.encoder(image_u8).unsqueeze(0)
        latent, state = run_lstm(self.lstm, features, state, episode_start.view(1, -1))
        latent = latent[0]
        return self.action_head(latent), self.value_head(latent), state

    def act(self, image_u8: torch.Tensor, h: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """One deterministic step from state (h, c) (already reset where an episode starts): (action (N, 1) in
        [-1, 1], h, c), as one traceable graph (the ONNX export's)."""
        features = self.encoder(image_u8).unsqueeze(0)
        latent, (h_new, c_new) = self.lstm(features, (h, c))
        return torch.clamp(self.action_head(latent[0]), -1.0, 1.0), h_new, c_new


class EnsembleNet(nn.Module):
    """Several `DrivingNet`s of one architecture (policies trained with different seeds) acting as one policy: the
    steering is the mean of the members' steering, each clipped to [-1, 1]; the value the mean of their values. The
    LSTM state is the members' states side by side along the hidden axis (layers, N, members x hidden), so that code
    written for one net (the rollout, the ONNX export) carries an ensemble's state unchanged.

    Why: policies of one recipe that differ only in their seed can carry different steering biases; the mean
    cancels biases that differ between members (experiments/NOTEBOOK.md). Weight names: `members.<k>.<DrivingNet
    name>`.
    """

    def __init__(self, members: Sequence[DrivingNet]) -> None:
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"an ensemble needs at least 2 members, got {len(members)}")
        self.members = nn.ModuleList(members)
        self.member_hidden_size = int(members[0].hidden_size)
        self.hidden_size = self.member_hidden_size * len(members)
        self.lstm_layers = int(members[0].lstm_layers)

    @property
    def log_std(self) -> torch.Tensor:
        """The members' mean log standard deviation (for stochastic actions)."""
        return torch.stack([m.log_std for m in self.members]).mean(0)

    def initial_state(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero LSTM state for n sequences: (h, c), each (layers, n, members x hidden)."""
        zeros = torch.zeros(self.lstm_layers, n, self.hidden_size)
        return zeros, zeros.clone()

    def _split(self, state: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return torch.split(state, self.member_hidden_size, dim=2)

    def step(
        self, image_u8: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor], episode_start: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """One time step for N sequences: (mean of the members' clipped steering (N, 1), mean value (N, 1), state)."""
        actions, values, hs, cs = [], [], [], []
        for member, h, c in zip(self.members, self._split(state[0]), self._split(state[1]), strict=True):
            mean, value, (h, c) = member.step(image_u8, (h.contiguous(), c.contiguous()), episode_start)
            actions.append(torch.clamp(mean, -1.0, 1.0))
            values.append(value)
            hs.append(h)
            cs.append(c)
        state_out = (torch.cat(hs, dim=2), torch.cat(cs, dim=2))
        return torch.stack(actions).mean(0), torch.stack(values).mean(0), state_out

    def act(self, image_u8: torch.Tensor, h: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """`DrivingNet.act` of every member on its part of the state, the actions averaged."""
        outputs = [
            member.act(image_u8, h_k.contiguous(), c_k.contiguous())
            for member, h_k, c_k in zip(self.members, self._split(h), self._split(c), strict=True)
        ]
        action = torch.stack([a for a, _, _ in outputs]).mean(0)
        return action, torch.cat([h for _, h, _ in outputs], dim=2), torch.cat([c for _, _, c in outputs], dim=2)


class ExportModule(nn.Module):
    """The deterministic policy for deployment (INTERFACES §4): one step with explicit LSTM state.

    forward(image_u8 (N,3,H,W) uint8, h (L,N,hidden), c (L,N,hidden), episode_start (N,) f32)
        -> (action (N,1) f32 in [-1, 1], h, c); the state is reset where episode_start == 1 before the step.
    """

    def __init__(self, net: DrivingNet | EnsembleNet) -> None:
        super().__init__()
        self.net = net
        self.lstm_layers = net.lstm_layers
        self.hidden_size = net.hidden_size

    def forward(
        self, image_u8: torch.Tensor, h: torch.Tensor, c: torch.Tensor, episode_start: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One deterministic step; see the class docstring."""
        keep = (1.0 - episode_start.float()).view(1, -1, 1)
        return self.net.act(image_u8, h * keep, c * keep)
