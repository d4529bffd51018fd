"""Keras models of thesis §7: Peak (§7.1) and Pressure (§7.2), built from a config.

Both map a normalized input grid to a normalized impulse grid, NHWC float32:

    (B, ny, nx, in_channels)  ->  (B, ny, nx, out_channels)

* **Peak** (§7.1, the thesis's own design): four 4x4 convolutions with 2x2
  average pooling between them; the raw input and each convolution's output
  (five scales) are reduced by a 1x1 convolution to one width, resized
  bilinearly to the input size and summed; then dense layers over the *whole*
  grid (Flatten -> Dense ... -> Dense(ny * nx * out) -> Reshape).  Dropout 0.4
  before every dense layer.  The dense layers fix the grid size
  (``fixed_grid=True`` in the model card).
* **Pressure** (§7.2, after Tompson et al. 2016): one 4x4 convolution, a
  pyramid of 2x2 average pools, a branch of 4x4 convolutions per scale,
  each branch resized bilinearly to the input size and summed, then 1x1
  convolutions.  No dropout.  Fully convolutional: the resize targets the
  *runtime* input size, so one model accepts any grid (``fixed_grid=False``).
* **UNet** (the architecture Tirca's Deep-Contact moved to): an encoder of
  3x3 convolutions with 2x2 average pools between levels, a decoder that
  resizes each level back to the one above and concatenates it with that
  level's encoder output (the skip that keeps contact-scale detail), then a
  linear 1x1 output.  Fully convolutional like Pressure.

Common to both (thesis §7): batch normalization after every convolution and
dense layer except the output layer, L2 regularization (lambda 0.01) on every
kernel, weights initialized from normal(0, 0.1), ReLU activations, a linear
output layer.  Widths and depths are config fields; configs are frozen
dataclasses that round-trip through JSON (``config_to_dict`` /
``config_from_dict``) and are stored in the run directory and the model card.

TensorFlow is imported only when a model is built, so the configs can be read
(by the exporter's card writer, the evaluator, the server) without it.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import tempfile
from dataclasses import dataclass
from typing import Any, Mapping

__all__ = [
    "PeakConfig",
    "PressureConfig",
    "UNetConfig",
    "build_model",
    "config_from_dict",
    "config_to_dict",
    "count_parameters",
    "default_config",
    "import_tensorflow",
]


@dataclass(frozen=True)
class PressureConfig:
    """Pressure model (thesis §7.2): fully convolutional, any grid size.

    stem_filters:   width of the first 4x4 convolution (full resolution).
    scales:         number of pyramid levels, full resolution included
                    (``scales - 1`` average pools of 2x2).
    branch_filters: widths of the 4x4 convolutions of each scale's branch;
                    the last width is the width of the summed features.
    head_filters:   widths of the 1x1 convolutions after the sum (before the
                    linear 1x1 output layer).
    """

    kind: str = "pressure"
    in_channels: int = 6
    out_channels: int = 2
    stem_filters: int = 16
    scales: int = 4
    branch_filters: tuple[int, ...] = (16, 16)
    head_filters: tuple[int, ...] = (32,)
    kernel_size: int = 4
    l2: float = 0.01
    init_std: float = 0.1
    batch_norm: bool = True

    fixed_grid = False  # class constant, not a field: Pressure takes any grid


@dataclass(frozen=True)
class PeakConfig:
    """Peak model (thesis §7.1): conv spine, five scales summed, dense layers.

    grid_shape:    (ny, nx) the model is built for (the dense layers fix it).
    conv_filters:  widths of the four 4x4 convolutions (2x2 average pools between).
    merge_filters: width every scale is reduced to by its 1x1 convolution.
    dense_units:   hidden dense layers (each sees the whole grid); the output
                   dense layer has ny * nx * out_channels units.
    dropout:       rate of the dropout before every dense layer.
    """

    kind: str = "peak"
    in_channels: int = 6
    out_channels: int = 2
    grid_shape: tuple[int, int] = (61, 61)
    conv_filters: tuple[int, ...] = (16, 32, 64, 128)
    merge_filters: int = 8
    dense_units: tuple[int, ...] = (512, 256)
    dropout: float = 0.4
    kernel_size: int = 4
    l2: float = 0.01
    init_std: float = 0.1
    batch_norm: bool = True

    fixed_grid = True


@dataclass(frozen=True)
class UNetConfig:
    """UNet: encoder-decoder with skips, fully convolutional, any grid size.

    widths: channels of each level, full resolution first (len(widths) - 1 pools).
    convs:  3x3 convolutions per level, in the encoder and again in the decoder.
    """

    kind: str = "unet"
    in_channels: int = 6
    out_channels: int = 2
    widths: tuple[int, ...] = (16, 32, 64)
    convs: int = 2
    kernel_size: int = 3
    l2: float = 0.0001
    init_std: float = 0.1
    batch_norm: bool = True

    fixed_grid = False


_CONFIGS = {"pressure": PressureConfig, "peak": PeakConfig, "unet": UNetConfig}


def default_config(kind: str, **overrides: Any):
    """The default config of ``kind`` ("pressure" or "peak") with ``overrides`` applied."""
    if kind not in _CONFIGS:
        raise ValueError(f"unknown model kind {kind!r}; known: {sorted(_CONFIGS)}")
    return config_from_dict({"kind": kind, **overrides})


def config_to_dict(config) -> dict[str, Any]:
    """Plain JSON-able dict (tuples become lists)."""
    return {f.name: (list(v) if isinstance(v := getattr(config, f.name), tuple) else v)
            for f in dataclasses.fields(config)}


def config_from_dict(data: Mapping[str, Any]):
    """Inverse of :func:`config_to_dict`; unknown keys or bad values raise ValueError."""
    if not isinstance(data, Mapping):
        raise ValueError(f"a model config is a JSON object, got {type(data).__name__}")
    kind = data.get("kind", "pressure")
    if kind not in _CONFIGS:
        raise ValueError(f"unknown model kind {kind!r}; known: {sorted(_CONFIGS)}")
    cls = _CONFIGS[kind]
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields)
    if unknown:
        raise ValueError(f"{kind} config: unknown keys {sorted(unknown)}; known: {sorted(fields)}")
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()}
    config = cls(**kw)
    _validate(config)
    return config


def _validate(config) -> None:
    def positive_ints(name: str, values) -> None:
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in values):
            raise ValueError(f"{config.kind} config: {name} must be positive integers, got {values!r}")

    positive_ints("in_channels/out_channels/kernel_size", (config.in_channels, config.out_channels, config.kernel_size))
    if not (config.l2 >= 0 and config.init_std > 0):
        raise ValueError(f"{config.kind} config: need l2 >= 0 and init_std > 0, got {config.l2!r}, {config.init_std!r}")
    if isinstance(config, UNetConfig):
        positive_ints("widths", config.widths)
        positive_ints("convs", (config.convs,))
        if not config.widths:
            raise ValueError("unet config: widths needs at least one level")
    elif isinstance(config, PressureConfig):
        positive_ints("stem_filters/scales", (config.stem_filters, config.scales))
        positive_ints("branch_filters", config.branch_filters)
        positive_ints("head_filters", config.head_filters)
        if not config.branch_filters:
            raise ValueError("pressure config: branch_filters needs at least one width")
    else:
        positive_ints("grid_shape", config.grid_shape)
        if len(config.grid_shape) != 2:
            raise ValueError(f"peak config: grid_shape must be (ny, nx), got {config.grid_shape!r}")
        positive_ints("conv_filters", config.conv_filters)
        positive_ints("merge_filters", (config.merge_filters,))
        positive_ints("dense_units", config.dense_units)
        if len(config.conv_filters) != 4:
            raise ValueError(f"peak config: conv_filters lists the four convolutions, got {config.conv_filters!r}")
        if not 0 <= config.dropout < 1:
            raise ValueError(f"peak config: dropout must be in [0, 1), got {config.dropout!r}")


# --------------------------------------------------------------------------- #
# Building (TensorFlow from here on)
# --------------------------------------------------------------------------- #


#: Lines TensorFlow's C++ side writes to stderr at import whatever
#: TF_CPP_MIN_LOG_LEVEL says (absl logs them before it is initialized).
_IMPORT_NOISE = ("All log messages before absl::InitializeLog()", "oneDNN custom operations are on")


def import_tensorflow():
    """Import TensorFlow quietly (Keras 3 on the TensorFlow backend) and return it."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    os.environ.setdefault("KERAS_BACKEND", "tensorflow")
    if "tensorflow" in sys.modules:
        return sys.modules["tensorflow"]
    # The C++ import messages bypass Python: capture file descriptor 2 while
    # importing and pass on every line that is not known noise.
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            import tensorflow as tf
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            captured.seek(0)
            for line in captured.read().decode(errors="replace").splitlines(keepends=True):
                if not any(n in line for n in _IMPORT_NOISE):
                    sys.stderr.write(line)
    return tf


_RESIZE_CLASS = None


def resize_like_layer():
    """The ``ResizeLike`` layer class: bilinear resize of x to the spatial size of a reference.

    ``ResizeLike()([x, ref])``: x (B, h, w, C), ref (B, H, W, *) -> (B, H, W, C).
    The size is read from ``tf.shape(ref)`` at run time, so the model stays
    fully convolutional and exports to ONNX as a Resize whose size is
    computed from the input's shape.
    """
    global _RESIZE_CLASS
    if _RESIZE_CLASS is None:
        tf = import_tensorflow()
        import keras

        @keras.saving.register_keras_serializable(package="deepcontact")
        class ResizeLike(keras.layers.Layer):
            def call(self, inputs):
                x, ref = inputs
                return tf.image.resize(x, tf.shape(ref)[1:3], method="bilinear")

            def compute_output_shape(self, input_shape):
                x, ref = input_shape
                return (x[0], ref[1], ref[2], x[3])

        _RESIZE_CLASS = ResizeLike
    return _RESIZE_CLASS


def build_model(config, name: str | None = None):
    """A Keras model for ``config`` (a :class:`PressureConfig` or :class:`PeakConfig`).

    Input "grids": (None, ny, nx, in_channels) float32 normalized grids, with
    ny, nx None for Pressure and ``config.grid_shape`` for Peak.  Output:
    (None, ny, nx, out_channels) normalized target grids.
    """
    _validate(config)
    if isinstance(config, PressureConfig):
        return _build_pressure(config, name or "pressure")
    if isinstance(config, PeakConfig):
        return _build_peak(config, name or "peak")
    if isinstance(config, UNetConfig):
        return _build_unet(config, name or "unet")
    raise ValueError(f"not a model config: {config!r}")


class _Layers:
    """Layer factories sharing the thesis's regularizer, initializer and BN rule."""

    def __init__(self, config):
        import_tensorflow()
        import keras

        self.keras = keras
        self.config = config
        self.n = 0

    def _kw(self) -> dict:
        k = self.keras
        return {
            "kernel_initializer": k.initializers.RandomNormal(0.0, self.config.init_std, seed=None),
            "kernel_regularizer": k.regularizers.L2(self.config.l2) if self.config.l2 else None,
        }

    def _bn_relu(self, x, name: str):
        k = self.keras
        if self.config.batch_norm:
            x = k.layers.BatchNormalization(name=f"{name}_bn")(x)
        return k.layers.ReLU(name=f"{name}_relu")(x)

    def conv(self, x, filters: int, size: int, name: str, *, output: bool = False):
        # No conv bias where batch norm follows: BN's beta is the bias.
        bias = output or not self.config.batch_norm
        x = self.keras.layers.Conv2D(filters, size, padding="same", use_bias=bias, name=name, **self._kw())(x)
        return x if output else self._bn_relu(x, name)

    def dense(self, x, units: int, name: str, *, output: bool = False):
        bias = output or not self.config.batch_norm
        x = self.keras.layers.Dense(units, use_bias=bias, name=name, **self._kw())(x)
        return x if output else self._bn_relu(x, name)

    def pool(self, x, name: str):
        # "same": odd sizes keep their last row/column (61 -> 31 -> 16 -> 8),
        # so the top and right edges of the grid reach the coarse scales.
        return self.keras.layers.AveragePooling2D(2, 2, padding="same", name=name)(x)


def _build_pressure(c: PressureConfig, name: str):
    L = _Layers(c)
    keras = L.keras
    ResizeLike = resize_like_layer()
    grids = keras.Input((None, None, c.in_channels), name="grids", dtype="float32")
    level = L.conv(grids, c.stem_filters, c.kernel_size, "stem")
    branches = []
    for s in range(c.scales):
        if s:
            level = L.pool(level, f"pool{s}")
        h = level
        for j, f in enumerate(c.branch_filters):
            h = L.conv(h, f, c.kernel_size, f"scale{s}_conv{j}")
        branches.append(h if s == 0 else ResizeLike(name=f"scale{s}_up")([h, grids]))
    h = keras.layers.Add(name="sum")(branches) if len(branches) > 1 else branches[0]
    for j, f in enumerate(c.head_filters):
        h = L.conv(h, f, 1, f"head{j}")
    out = L.conv(h, c.out_channels, 1, "impulses", output=True)
    return keras.Model(grids, out, name=name)


def _build_peak(c: PeakConfig, name: str):
    L = _Layers(c)
    keras = L.keras
    ResizeLike = resize_like_layer()
    ny, nx = c.grid_shape
    grids = keras.Input((ny, nx, c.in_channels), name="grids", dtype="float32")
    scales = [grids]
    h = grids
    for j, f in enumerate(c.conv_filters):
        if j:
            h = L.pool(h, f"pool{j}")
        h = L.conv(h, f, c.kernel_size, f"conv{j}")
        scales.append(h)
    merged = []
    for s, x in enumerate(scales):
        x = L.conv(x, c.merge_filters, 1, f"merge{s}")
        merged.append(x if x.shape[1:3] == (ny, nx) else ResizeLike(name=f"merge{s}_up")([x, grids]))
    h = keras.layers.Add(name="sum")(merged)
    h = keras.layers.Flatten(name="flatten")(h)
    for j, u in enumerate(c.dense_units):
        h = keras.layers.Dropout(c.dropout, name=f"dense{j}_dropout")(h)
        h = L.dense(h, u, f"dense{j}")
    h = keras.layers.Dropout(c.dropout, name="out_dropout")(h)
    h = L.dense(h, ny * nx * c.out_channels, "out_dense", output=True)
    out = keras.layers.Reshape((ny, nx, c.out_channels), name="impulses")(h)
    return keras.Model(grids, out, name=name)


def _build_unet(c: UNetConfig, name: str):
    L = _Layers(c)
    keras = L.keras
    ResizeLike = resize_like_layer()
    grids = keras.Input((None, None, c.in_channels), name="grids", dtype="float32")
    skips, h = [], grids
    for level, width in enumerate(c.widths):
        if level:
            h = L.pool(h, f"pool{level}")
        for j in range(c.convs):
            h = L.conv(h, width, c.kernel_size, f"enc{level}_conv{j}")
        skips.append(h)
    for level in range(len(c.widths) - 2, -1, -1):
        # Back to this level's size (odd sizes included), then its encoder's features alongside.
        h = ResizeLike(name=f"up{level}")([h, skips[level]])
        h = keras.layers.Concatenate(name=f"skip{level}")([h, skips[level]])
        for j in range(c.convs):
            h = L.conv(h, c.widths[level], c.kernel_size, f"dec{level}_conv{j}")
    out = L.conv(h, c.out_channels, 1, "impulses", output=True)
    return keras.Model(grids, out, name=name)


def count_parameters(model) -> dict[str, int]:
    """{"total", "trainable"} parameter counts (batch-norm moving statistics are non-trainable)."""
    import numpy as np

    trainable = int(sum(np.prod(v.shape) for v in model.trainable_weights))
    total = int(sum(np.prod(v.shape) for v in model.weights))
    return {"total": total, "trainable": trainable}
