"""Piecewise-planar worlds: textured parallelograms, and builders for rooms, boxes and trees.

A world is a set of R parallelograms in world coordinates (metres, z up by
the presets' convention, though nothing here assumes it). Parallelogram ``r``
is the set of points ``origin + s * edge_u + t * edge_v`` with ``s, t`` in
[0, 1]; a rectangle is the case ``edge_u . edge_v = 0``. Its texture
coordinates (level-0 texels) are the affine map ``texel_map @ (s, t, 1)``,
so adjacent patches can share a continuous texture (terrain) and one texture
can be placed anywhere, scaled and sheared. Surfaces are two-sided.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cmax.sim.textures import Texture, make_texture

__all__ = ["PlanarWorld", "WorldBuilder"]


@dataclass(frozen=True, eq=False)
class PlanarWorld:
    """R textured parallelograms (struct of arrays) and their textures.

    Attributes
    ----------
    origins, edges_u, edges_v : ndarray, shape (R, 3), float64
        Corner and edge vectors in world coordinates [m].
    texture_ids : ndarray, shape (R,), int64
        Index into ``textures``.
    texel_maps : ndarray, shape (R, 2, 3), float64
        ``(texel_x, texel_y) = texel_maps[r] @ (s, t, 1)`` in level-0 texels.
    gains : ndarray, shape (R,), float64
        Brightness factor of each surface (static shading), intensity =
        gain * texture value, clipped to 255.
    textures : list of Texture
    facing : ndarray, shape (R,), int8, optional
        Visible side: +1 the side of the normal ``edge_u x edge_v``, -1 the
        other side, 0 both (default). One-sided faces of closed objects let the
        renderer skip back faces.
    """

    origins: np.ndarray
    edges_u: np.ndarray
    edges_v: np.ndarray
    texture_ids: np.ndarray
    texel_maps: np.ndarray
    gains: np.ndarray
    textures: list[Texture]
    facing: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.origins)
        facing = np.zeros(n, np.int8) if self.facing is None else np.asarray(self.facing, dtype=np.int8)
        if facing.shape != (n,) or not np.isin(facing, (-1, 0, 1)).all():
            raise ValueError(f"facing must have shape ({n},) with values -1, 0, 1")
        object.__setattr__(self, "facing", facing)
        if n == 0:
            raise ValueError("a world needs at least one parallelogram")
        if n >= 1 << 16:
            raise ValueError(f"at most 65535 parallelograms are supported, got {n}")
        for name, shape in (("origins", (n, 3)), ("edges_u", (n, 3)), ("edges_v", (n, 3)),
                            ("texture_ids", (n,)), ("texel_maps", (n, 2, 3)), ("gains", (n,))):
            value = np.asarray(getattr(self, name))
            if value.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {value.shape}")
            if not np.isfinite(value).all():
                raise ValueError(f"{name} must be finite")
        normals = np.cross(self.edges_u, self.edges_v)
        if np.any(np.linalg.norm(normals, axis=1) <= 1e-12):
            raise ValueError("every parallelogram needs two non-parallel, non-zero edges")
        ids = np.asarray(self.texture_ids)
        if ids.min() < 0 or ids.max() >= len(self.textures):
            raise ValueError(f"texture_ids must index the {len(self.textures)} textures")

    def __len__(self) -> int:
        return len(self.origins)

    @property
    def cutout(self) -> np.ndarray:
        """(R,) bool: parallelograms whose texture has an alpha mask."""
        has_alpha = np.array([t.alpha is not None for t in self.textures])
        return has_alpha[self.texture_ids]

    def corners(self) -> np.ndarray:
        """(R, 4, 3) corners in the order origin, +u, +u+v, +v [m]."""
        o, u, v = self.origins, self.edges_u, self.edges_v
        return np.stack([o, o + u, o + u + v, o + v], axis=1)


@dataclass
class WorldBuilder:
    """Collects parallelograms and textures, then :meth:`build` freezes them.

    Parameters
    ----------
    rng : numpy Generator
        Source of random texture offsets (deterministic scenes for a seed).
    texture_size : int
        Side of procedural textures (texels).
    """

    rng: np.random.Generator
    texture_size: int = 512
    _quads: list[tuple] = field(default_factory=list)
    _textures: list[Texture] = field(default_factory=list)

    # -- textures ---------------------------------------------------------------------
    def texture(self, texture: Texture | str, seed: int | None = None) -> int:
        """Register a texture (a :class:`Texture` or a procedural kind); returns its id."""
        if isinstance(texture, str):
            seed = int(self.rng.integers(1 << 31)) if seed is None else seed
            texture = make_texture(texture, seed, self.texture_size)
        self._textures.append(texture)
        return len(self._textures) - 1

    # -- primitives -------------------------------------------------------------------
    def quad(
        self, origin, edge_u, edge_v, texture: int, *, texels_per_metre: float = 64.0,
        texel_map: np.ndarray | None = None, gain: float = 1.0, random_offset: bool = True,
        facing=None,
    ) -> None:
        """Add the parallelogram ``origin + s*edge_u + t*edge_v`` with texture id ``texture``.

        By default the texture is laid at ``texels_per_metre`` along both edges
        from a random offset; ``texel_map`` (2, 3) overrides that mapping.
        ``facing`` (a direction, world frame) makes the face one-sided, visible
        only from the half-space it points into; ``None`` keeps it two-sided.
        """
        origin, edge_u, edge_v = (np.asarray(x, dtype=np.float64) for x in (origin, edge_u, edge_v))
        if texel_map is None:
            offset = self.rng.uniform(0, self.texture_size, 2) if random_offset else np.zeros(2)
            texel_map = np.array([
                [np.linalg.norm(edge_u) * texels_per_metre, 0.0, offset[0]],
                [0.0, np.linalg.norm(edge_v) * texels_per_metre, offset[1]],
            ])
        side = 0
        if facing is not None:
            side = int(np.sign(np.cross(edge_u, edge_v) @ np.asarray(facing, dtype=np.float64)))
            if side == 0:
                raise ValueError("facing must not lie in the plane of the parallelogram")
        self._quads.append((origin, edge_u, edge_v, int(texture), np.asarray(texel_map, float), float(gain), side))

    def image_quad(self, origin, edge_u, edge_v, texture: int, *, gain: float = 1.0, facing=None) -> None:
        """Add a parallelogram showing the whole texture once (billboards, pictures).

        Texel (0, 0) sits at ``origin``; the texture's x runs along ``edge_u``
        and its y along ``edge_v``.
        """
        size = self.texture_size
        texel_map = np.array([[size, 0.0, 0.0], [0.0, size, 0.0]])
        self.quad(origin, edge_u, edge_v, texture, texel_map=texel_map, gain=gain, facing=facing)

    def box(self, centre, size, yaw: float, textures: int | tuple[int, int], *,
            texels_per_metre: float = 64.0, gains: tuple[float, float, float] = (1.0, 0.8, 0.6),
            bottom: bool = False, fit_sides: bool = False) -> None:
        """An axis-aligned (z up) box rotated by ``yaw`` about z: 4 sides, a top, optionally a bottom.

        ``textures`` is one id or (sides, top); ``gains`` shade the sides facing
        +x/-x, +y/-y and the top differently (static lighting). With
        ``fit_sides`` each side shows its whole texture once (upright), e.g. a
        car's side; otherwise textures repeat at ``texels_per_metre``.
        """
        side_tex, top_tex = (textures, textures) if isinstance(textures, int) else textures
        c = np.asarray(centre, float)
        sx, sy, sz = (np.asarray(size, float) / 2.0)
        cos, sin = np.cos(yaw), np.sin(yaw)
        ex = np.array([cos, sin, 0.0])
        ey = np.array([-sin, cos, 0.0])
        ez = np.array([0.0, 0.0, 1.0])
        sides = [  # (origin, along, gain, outward): faces +x, -x, +y, -y, seen upright from outside
            (c + sx * ex - sy * ey + sz * ez, 2 * sy * ey, gains[0], ex),
            (c - sx * ex + sy * ey + sz * ez, -2 * sy * ey, gains[0] * 0.85, -ex),
            (c + sx * ex + sy * ey + sz * ez, -2 * sx * ex, gains[1], ey),
            (c - sx * ex - sy * ey + sz * ez, 2 * sx * ex, gains[1] * 0.9, -ey),
        ]
        for origin, along, gain, outward in sides:  # closed box: faces are one-sided
            if fit_sides:
                self.image_quad(origin, along, -2 * sz * ez, side_tex, gain=gain, facing=outward)
            else:
                self.quad(origin, along, -2 * sz * ez, side_tex, gain=gain, texels_per_metre=texels_per_metre,
                          facing=outward)
        kw = {"texels_per_metre": texels_per_metre}
        self.quad(c - sx * ex - sy * ey + sz * ez, 2 * sx * ex, 2 * sy * ey, top_tex, gain=gains[2] * 1.4,
                  facing=ez, **kw)
        if bottom:
            self.quad(c - sx * ex - sy * ey - sz * ez, 2 * sx * ex, 2 * sy * ey, top_tex, gain=gains[2] * 0.6,
                      facing=-ez, **kw)

    def tree(self, base, *, height: float, crown_radius: float, trunk_texture: int,
             crown_texture: int, facing_yaw: float, crossed: bool = True) -> None:
        """A tree as billboards: a trunk (two crossed strips) and a cut-out crown.

        The crown is one square cut-out billboard (two when ``crossed``, at
        right angles) of side ``2*crown_radius`` whose centre is at
        ``height - crown_radius``; ``facing_yaw`` orients it (a billboard facing
        the camera's main direction of travel looks best).
        """
        base = np.asarray(base, float)
        trunk_w = max(0.12, 0.08 * crown_radius)
        ez = np.array([0.0, 0.0, 1.0])
        trunk_h = height - crown_radius
        for yaw in (facing_yaw, facing_yaw + np.pi / 2):
            e = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            self.quad(base - trunk_w / 2 * e, trunk_w * e, trunk_h * ez, trunk_texture,
                      texels_per_metre=200.0, gain=0.8)
        yaws = (facing_yaw, facing_yaw + np.pi / 2) if crossed else (facing_yaw,)
        top = base + height * ez
        for yaw in yaws:
            e = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            self.image_quad(top - crown_radius * e, 2 * crown_radius * e, -2 * crown_radius * ez, crown_texture)

    def build(self) -> PlanarWorld:
        if not self._quads:
            raise ValueError("no parallelograms were added")
        columns = list(zip(*self._quads))
        return PlanarWorld(
            np.stack(columns[0]), np.stack(columns[1]), np.stack(columns[2]),
            np.array(columns[3], dtype=np.int64), np.stack(columns[4]), np.array(columns[5]),
            list(self._textures), np.array(columns[6], dtype=np.int8),
        )
