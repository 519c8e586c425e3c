"""The depth-pose network: an encoder-decoder with skip connections on the event volume, and a pose head.

Input: the 5-bin event volume (B, bins, H, W) of :func:`cmax.representations.voxel_grid`
(EvtSlowTV section 4.1). The encoder halves the resolution ``levels`` times
(channels ``width * 2**k``); the decoder upsamples back, concatenating the
encoder feature of the same scale (U-Net skips), and predicts an inverse depth
at every decoder scale, bounded to the configured depth range:

    rho = 1/z_max + (1/z_min - 1/z_max) * sigmoid(logit)      [1/m]

The pose head on the bottleneck (conv, mean over a grid of cells, linear) gives the twist
``(v [m/s], omega [rad/s])`` of the window, each scaled by a configured
typical magnitude (``tanh`` bounded). With ``odd_twist`` the ``tanh`` reads half the difference of
the head's linear outputs for the window and for its time reversal (a window played backwards gets exactly
the negated twist).
Inputs whose sides are not multiples of ``2**levels`` are zero-padded and the outputs cropped back.

:class:`ModelConfig` also shapes the network for speed: ``block`` (dense 3x3 or
depthwise-separable convolutions), ``norm`` (GroupNorm or none) and
``space_to_depth`` (the U-Net runs at half resolution on 2x2-folded input and
its finest output is unfolded back). Its defaults are the original network;
:meth:`ModelConfig.fast` is the recommended fast one.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

__all__ = ["ModelConfig", "DepthPoseNet", "NetOutput", "BLOCKS", "NORMS"]

BLOCKS = ("dense", "separable")
NORMS = ("group", "none")


@dataclass(frozen=True)
class ModelConfig:
    """Size and output ranges of :class:`DepthPoseNet`.

    Attributes
    ----------
    bins : int
        Time bins of the input event volume.
    width : int
        Channels of the first encoder level (doubled per level).
    levels : int
        Encoder levels (each halves the resolution).
    min_depth, max_depth : float
        Depth range [m] of the inverse-depth outputs.
    max_speed : float
        Bound of each component of ``v`` [m/s].
    max_angular_speed : float
        Bound of each component of ``omega`` [rad/s].
    block : {"dense", "separable"}
        Convolution block: ``"dense"``, two 3x3 convolutions (the original network);
        ``"separable"``, two depthwise 3x3 + pointwise 1x1 pairs (about 8x fewer
        multiply-adds at the same width).
    norm : {"group", "none"}
        Normalisation after each convolution of a block: ``"group"`` (per-sample GroupNorm,
        the original network) or ``"none"`` (biased convolutions, no normalisation).
    space_to_depth : bool
        ``True``: fold each 2x2 pixel block of the input into channels (``pixel_unshuffle``,
        ``4 * bins`` channels at half resolution), run the U-Net there with ``levels - 1``
        levels, and unfold the finest inverse depth back to full resolution
        (``pixel_shuffle`` of a 4-channel head): no full-resolution feature maps, the same
        output scales. ``False``: the original network.
    pose_cells : int
        The pose head averages the bottleneck over a ``pose_cells`` x ``pose_cells`` grid of cells
        before its linear layer. 1 (the original network) is a global mean, which discards where in
        the image a feature is: expansion and contraction (forward and backward motion), or a pan left
        and right at the two sides, average alike. 3 keeps the layout the motion field needs.
    odd_twist : bool
        ``True``: the twist is odd under time reversal by construction, ``twist(V) = s * tanh((h(V) - h(R V)) / 2)``
        with ``h`` the pose head's linear output, ``s`` the typical magnitudes and ``R V = -V[::-1]`` (bins reversed,
        signs flipped: the volume of the window played backwards, :func:`learned.data.reverse_time`), so that a
        window played backwards gets exactly ``-twist`` (the encoder runs on both volumes; the depth is the
        window's own). The difference is taken before the ``tanh``: the part of ``h`` the two volumes share, which
        no loss sees, cancels instead of saturating the ``tanh`` (a twist of exactly 0 with no gradient).
        ``False`` (the original network): ``s * tanh(h(V))``.
    """

    bins: int = 5
    width: int = 16
    levels: int = 4
    min_depth: float = 0.5
    max_depth: float = 60.0
    max_speed: float = 15.0
    max_angular_speed: float = 3.0
    block: str = "dense"
    norm: str = "group"
    space_to_depth: bool = False
    pose_cells: int = 1
    odd_twist: bool = False

    def __post_init__(self) -> None:
        for name in ("bins", "width", "levels", "pose_cells"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
                raise ValueError(f"model.{name} must be a positive integer, got {getattr(self, name)!r}")
        if self.block not in BLOCKS:
            raise ValueError(f"model.block must be one of {BLOCKS}, got {self.block!r}")
        if self.norm not in NORMS:
            raise ValueError(f"model.norm must be one of {NORMS}, got {self.norm!r}")
        for name in ("space_to_depth", "odd_twist"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"model.{name} must be true or false, got {getattr(self, name)!r}")
        if self.norm == "group":
            for k in range(self.inner_levels + 1):
                c = self.width * 2 ** k
                if c % min(8, c):
                    raise ValueError(f"model.width={self.width} gives {c} channels at level {k}, which GroupNorm's "
                                     f"{min(8, c)} groups do not divide: use a width that is a power of two or "
                                     "a multiple of 8")
        if not (0 < self.min_depth < self.max_depth):
            raise ValueError(f"need 0 < model.min_depth < model.max_depth, got {self.min_depth}, {self.max_depth}")
        if self.max_speed <= 0 or self.max_angular_speed <= 0:
            raise ValueError("model.max_speed and model.max_angular_speed must be positive")

    @property
    def inner_levels(self) -> int:
        """Levels of the U-Net proper (``levels - 1`` with ``space_to_depth``)."""
        return self.levels - int(self.space_to_depth)

    @classmethod
    def fast(cls, **changes) -> "ModelConfig":
        """The recommended fast network: ``space_to_depth=True`` (width 16, dense blocks, GroupNorm, 4 levels).

        Other fields as given in ``changes``, else the defaults. In a config file: ``space_to_depth = true``
        under ``[model]`` (or the override ``model.space_to_depth=true``). The defaults of
        :class:`ModelConfig` stay the original network, so that configs and checkpoints written before
        ``block``, ``norm`` and ``space_to_depth`` existed rebuild it. See
        ``benchmarks/results/speed_learned.md`` for its speed against the original network.
        """
        return cls(**{"space_to_depth": True, **changes})


@dataclass(frozen=True, eq=False)
class NetOutput:
    """Outputs of :class:`DepthPoseNet`.

    Attributes
    ----------
    inverse_depths : tuple of Tensor (B, 1, H/2**s, W/2**s)
        Inverse depth [1/m] at each decoder scale, finest first (``[0]`` is full resolution).
    twist : Tensor (B, 6)
        ``(v [m/s], omega [rad/s])``.
    """

    inverse_depths: tuple[torch.Tensor, ...]
    twist: torch.Tensor

    @property
    def inverse_depth(self) -> torch.Tensor:
        """The full-resolution inverse depth (B, 1, H, W) [1/m]."""
        return self.inverse_depths[0]

    @property
    def depth(self) -> torch.Tensor:
        """Full-resolution z-depth (B, 1, H, W) [m]."""
        return 1.0 / self.inverse_depths[0]


def _norm_act(channels: int, norm: str) -> list[nn.Module]:
    """GroupNorm (per sample: no batch statistics, so ranks agree with one process) or nothing, then LeakyReLU."""
    return ([nn.GroupNorm(min(8, channels), channels)] if norm == "group" else []) + [nn.LeakyReLU(0.1)]


def _block(cin: int, cout: int, stride: int, block: str = "dense", norm: str = "group") -> nn.Sequential:
    """Two convolutions (the first with ``stride``), each followed by ``norm`` and LeakyReLU.

    ``block="dense"``: 3x3 convolutions; ``"separable"``: depthwise 3x3 then pointwise 1x1.
    No conv bias before a norm: its gradient is zero up to rounding, which Adam would amplify into noise.
    """
    bias = norm == "none"
    layers: list[nn.Module] = []
    for a, b, s in ((cin, cout, stride), (cout, cout, 1)):
        if block == "dense":
            layers.append(nn.Conv2d(a, b, 3, s, 1, bias=bias))
        else:
            layers += [nn.Conv2d(a, a, 3, s, 1, groups=a, bias=False), nn.Conv2d(a, b, 1, bias=bias)]
        layers += _norm_act(b, norm)
    return nn.Sequential(*layers)


class DepthPoseNet(nn.Module):
    """U-Net depth decoder and bottleneck pose head (see the module docstring), shaped by ``config``;
    ``channels_last``: run the convolutions in that memory format (faster on the CPU).

    Examples
    --------
    >>> import torch
    >>> net = DepthPoseNet(ModelConfig(width=4, levels=2))
    >>> out = net(torch.zeros(2, 5, 30, 41))
    >>> out.inverse_depth.shape, out.twist.shape
    (torch.Size([2, 1, 30, 41]), torch.Size([2, 6]))
    """

    def __init__(self, config: ModelConfig = ModelConfig(), *, channels_last: bool = True) -> None:
        """``channels_last``: weights and activations in NHWC, the layout oneDNN's CPU convolutions are
        fastest in (same results to float rounding); ``False`` keeps NCHW, the original network's layout."""
        super().__init__()
        self.config = config
        self.memory_format = torch.channels_last if channels_last else torch.contiguous_format
        levels = config.inner_levels
        c = [config.width * 2 ** k for k in range(levels + 1)]
        kind = {"block": config.block, "norm": config.norm}
        self.stem = _block(config.bins * (4 if config.space_to_depth else 1), c[0], 1, **kind)
        self.down = nn.ModuleList(_block(c[k], c[k + 1], 2, **kind) for k in range(levels))
        self.up = nn.ModuleList(_block(c[k + 1] + c[k], c[k], 1, **kind) for k in reversed(range(levels)))
        self.heads = nn.ModuleList(nn.Conv2d(c[k], 1, 3, 1, 1) for k in reversed(range(levels)))
        if config.space_to_depth:   # the full-resolution inverse depth, as 2x2 blocks of the finest features
            self.full_head = nn.Conv2d(c[0], 4, 3, 1, 1)
        self.pose = nn.Sequential(nn.Conv2d(c[-1], c[-1], 3, 1, 1), nn.LeakyReLU(0.1))
        self.pose_pool = nn.AdaptiveAvgPool2d(config.pose_cells)
        self.pose_out = nn.Linear(c[-1] * config.pose_cells ** 2, 6)
        nn.init.zeros_(self.pose_out.weight)
        nn.init.zeros_(self.pose_out.bias)
        self.to(memory_format=self.memory_format)

    def _bounded(self, logits: torch.Tensor) -> torch.Tensor:
        lo, hi = 1.0 / self.config.max_depth, 1.0 / self.config.min_depth
        return lo + (hi - lo) * torch.sigmoid(logits)

    def forward(self, volume: torch.Tensor) -> NetOutput:
        """Inverse depths and twist of event volumes ``volume`` (B, bins, H, W) float32."""
        if volume.dim() != 4 or volume.shape[1] != self.config.bins:
            raise ValueError(f"volume must have shape (B, {self.config.bins}, H, W), got {tuple(volume.shape)}")
        H, W = volume.shape[-2:]
        n = volume.shape[0]
        if self.config.odd_twist:   # the window and the window played backwards, through one encoder pass
            volume = torch.cat([volume, -volume.flip(1)])
        m = 2 ** self.config.levels
        x = F.pad(volume, (0, (-W) % m, 0, (-H) % m))
        inner = F.pixel_unshuffle(x, 2) if self.config.space_to_depth else x
        skips = [self.stem(inner.contiguous(memory_format=self.memory_format))]
        for down in self.down:
            skips.append(down(skips[-1]))
        feature = skips.pop()
        pooled = self.pose_pool(self.pose(feature)).flatten(1)
        scale = torch.tensor([self.config.max_speed] * 3 + [self.config.max_angular_speed] * 3,
                             dtype=pooled.dtype, device=pooled.device)
        logit = self.pose_out(pooled)
        if self.config.odd_twist:   # odd before the (odd) tanh: the part both passes share cancels, never saturates it
            logit = (logit[:n] - logit[n:]) / 2
            feature, skips = feature[:n], [skip[:n] for skip in skips]
        twist = torch.tanh(logit) * scale
        outputs = []
        for up, head in zip(self.up, self.heads):
            skip = skips.pop()
            feature = up(torch.cat([F.interpolate(feature, size=skip.shape[-2:], mode="bilinear",
                                                  align_corners=False), skip], 1))
            outputs.append(self._bounded(head(feature)))
        if self.config.space_to_depth:
            outputs.append(self._bounded(F.pixel_shuffle(self.full_head(feature), 2)))
        crops = []
        for out in reversed(outputs):   # finest first, cropped to the input's extent at that scale
            s = x.shape[-1] // out.shape[-1]
            crops.append(out[..., : -(-H // s), : -(-W // s)])
        return NetOutput(tuple(crops), twist)
