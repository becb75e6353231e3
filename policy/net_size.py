"""The size of a driving network (policy/net.py::DrivingNet), counted from its architecture alone.

A config or a run folder's policy.json can describe a network that would take all the memory there is (a 85 GB
linear layer from a typo in `features_dim`); it is refused with one line *before* torch allocates anything.
Counted by hand (not by building the module) because building it is exactly what must not happen.
"""

from __future__ import annotations

from collections.abc import Sequence

MAX_PARAMETERS = 100_000_000
"""Largest network accepted: 100 M parameters, 0.4 GB of float32 (x4 with Adam's moments and the gradients)."""
MAX_ACTIVATIONS_PER_IMAGE = 50_000_000
"""Largest convolution output per image accepted (floats summed over the layers): 0.2 GB per image."""


def _conv_out(size_px: int, kernel: int, stride: int) -> int:
    return (size_px - kernel) // stride + 1


def _conv_size(
    observation_shape: Sequence[int], conv_layers: Sequence[Sequence[int]], input_pool: int
) -> tuple[int, int, int]:
    """(parameters, activations per image, output values) of the pooling and convolutions in front of the linear
    layer; ValueError when they shrink the image to nothing or a size is not positive."""
    channels, height, width = (int(v) for v in observation_shape)
    height, width = height // input_pool, width // input_pool
    params, activations = 0, 0
    in_ch = channels
    for layer in conv_layers:
        out_ch, kernel, stride = (int(v) for v in layer)
        if min(out_ch, kernel, stride) < 1:
            raise ValueError(f"conv layer {list(layer)}: channels, kernel and stride must be at least 1")
        params += out_ch * (in_ch * kernel * kernel + 1)
        height, width = _conv_out(height, kernel, stride), _conv_out(width, kernel, stride)
        if height < 1 or width < 1:
            raise ValueError(
                f"conv layers {[list(c) for c in conv_layers]} shrink the {observation_shape} image to nothing"
            )
        activations += out_ch * height * width
        in_ch = out_ch
    return params, activations, in_ch * height * width


def check_network_size(
    observation_shape: Sequence[int],
    conv_layers: Sequence[Sequence[int]],
    features_dim: int,
    lstm_hidden_size: int,
    lstm_layers: int,
    input_pool: int = 1,
) -> int:
    """The parameter count of the DrivingNet with this architecture; ValueError (one line) when it is absurdly large,
    shrinks the image away or has a size that is not positive."""
    if min(*(int(v) for v in observation_shape), features_dim, lstm_hidden_size, lstm_layers, input_pool) < 1:
        raise ValueError("every size of the network must be at least 1")
    params, activations, conv_out = _conv_size(observation_shape, conv_layers, input_pool)
    params += conv_out * features_dim + features_dim  # the linear layer after the convolutions
    lstm_in = features_dim
    for _ in range(lstm_layers):
        params += 4 * lstm_hidden_size * (lstm_in + lstm_hidden_size + 2)
        lstm_in = lstm_hidden_size
    params += 2 * (lstm_hidden_size + 1) + 1  # steering and value heads, log std
    if params > MAX_PARAMETERS:
        raise ValueError(
            f"the network would have {params / 1e6:,.0f} M parameters ({4 * params / 1e9:,.1f} GB of float32); "
            f"at most {MAX_PARAMETERS / 1e6:.0f} M are accepted (check policy.features_dim, lstm_hidden_size and "
            "conv_layers)"
        )
    if activations > MAX_ACTIVATIONS_PER_IMAGE:
        raise ValueError(
            f"the convolutions would output {activations / 1e6:,.0f} M values per image; at most "
            f"{MAX_ACTIVATIONS_PER_IMAGE / 1e6:.0f} M are accepted (check policy.conv_layers and input_pool)"
        )
    return params
