"""Layouts of cube blocks (Loos et al. 2011, §6.1): the pure geometry that the Mitsuba scene kind
``"blocks"`` (``jprt.render.scenes``) and Modular Radiance Transfer (``jprt.methods.mrt``) share.

A **block** is a unit cube ``[0, 1]^3`` (y up) with a floor, a ceiling and four side walls, each
side either a wall or *missing* (an interface to the neighbouring block). Side ``k`` has the
outward normal ``SIDE_NORMALS[k]`` (+x, +z, -x, -z): one 90-degree turn about the vertical axis
(``rotate_points``) takes side ``k`` to side ``k + 1``.

Every face carries a ``t x t`` texel grid; texel ``f * t^2 + j * t + i`` is at
``FACE_ORIGINS[f] + (i + 1/2) / t * FACE_U[f] + (j + 1/2) / t * FACE_V[f]``, facing
``FACE_NORMALS[f]`` (inward). Faces are 0 floor, 1 ceiling, 2 + k side k. A turn of the block is a
permutation of its texels (``rotation_permutation``).

The **2D-maze dictionary** (§6.1): up to rotation, six blocks with 0 to 4 sides missing and 12
missing sides in all (``DICTIONARY``, canonical masks). A **layout** is a set of grid cells and
the open edges between 4-adjacent cells (any graph on the grid: corridors, trees, cycles);
``Layout.blocks`` gives each cell its dictionary type and the turn that maps the canonical block
onto it.
"""

from __future__ import annotations

import functools
from typing import NamedTuple, Sequence

import numpy as np

__all__ = ["SIDE_NORMALS", "SIDE_STEPS", "FACE_ORIGINS", "FACE_U", "FACE_V", "FACE_NORMALS", "DICTIONARY",
           "texel_centres", "texel_count", "rotate_points", "rotate_directions", "rotation_permutation",
           "rotate_pattern", "locate", "exit_face", "Layout", "Block", "corridor", "grid", "random_maze",
           "layout_from_dict", "texel_albedo"]

#: Outward normals of the four sides (x, y, z), side k + 1 is side k turned once.
SIDE_NORMALS = np.array([[1, 0, 0], [0, 0, 1], [-1, 0, 0], [0, 0, -1]], np.float64)
#: Grid step (di, dj) across each side; cell (i, j) sits at x = i, z = j.
SIDE_STEPS = ((1, 0), (0, 1), (-1, 0), (0, -1))

FACE_ORIGINS = np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 0]], np.float64)
FACE_U = np.array([[1, 0, 0], [1, 0, 0], [0, 0, 1], [1, 0, 0], [0, 0, 1], [1, 0, 0]], np.float64)
FACE_V = np.array([[0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0]], np.float64)
FACE_NORMALS = np.array([[0, 1, 0], [0, -1, 0], [-1, 0, 0], [0, 0, -1], [1, 0, 0], [0, 0, 1]], np.float64)
FACE_NAMES = ("floor", "ceiling", "side0", "side1", "side2", "side3")

#: The 2D-maze dictionary (§6.1): name -> missing sides of the canonical block.
DICTIONARY: dict[str, tuple[int, ...]] = {
    "closed": (),
    "end": (0,),
    "corner": (0, 1),
    "straight": (0, 2),
    "tee": (0, 1, 2),
    "cross": (0, 1, 2, 3),
}


def texel_count(t: int) -> int:
    """Texels of one block: 6 faces of t x t (missing faces keep their slots, always zero)."""
    return 6 * int(t) ** 2


@functools.lru_cache(maxsize=16)
def _centres(t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g = (np.arange(t) + 0.5) / t
    uu, vv = np.meshgrid(g, g, indexing="xy")  # (j, i): row j, column i
    pos = (FACE_ORIGINS[:, None, None] + uu[None, ..., None] * FACE_U[:, None, None]
           + vv[None, ..., None] * FACE_V[:, None, None]).reshape(-1, 3)
    normal = np.repeat(FACE_NORMALS, t * t, axis=0)
    face = np.repeat(np.arange(6), t * t)
    return pos, normal, face


def texel_centres(t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 3) positions in the unit block, (n, 3) inward normals and (n,) face of every texel."""
    pos, normal, face = _centres(int(t))
    return pos.copy(), normal.copy(), face.copy()


def rotate_points(p, turns: int):
    """Turn points of the unit block ``turns`` times by 90 degrees about its vertical axis
    (x, z) -> (1 - z, x): side k goes to side k + turns."""
    p = np.array(p, np.float64)
    for _ in range(int(turns) % 4):
        p = np.stack([1.0 - p[..., 2], p[..., 1], p[..., 0]], axis=-1)
    return p


def rotate_directions(d, turns: int):
    """The same turn for directions: (dx, dz) -> (-dz, dx)."""
    d = np.array(d, np.float64)
    for _ in range(int(turns) % 4):
        d = np.stack([-d[..., 2], d[..., 1], d[..., 0]], axis=-1)
    return d


def locate(points, t: int, normals=None) -> np.ndarray:
    """Texel index of points on the block's faces (the face whose plane is nearest; with
    ``normals``, the face whose inward normal matches best breaks ties at edges)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    dist = np.stack([np.abs((p - FACE_ORIGINS[f]) @ FACE_NORMALS[f]) for f in range(6)], -1)
    if normals is not None:
        n = np.asarray(normals, np.float64).reshape(-1, 3)
        dist = dist - 1e-6 * (n @ FACE_NORMALS.T)
    face = np.argmin(dist, axis=-1)
    rel = p - FACE_ORIGINS[face]
    i = np.clip(np.floor(np.sum(rel * FACE_U[face], -1) * t), 0, t - 1).astype(np.int64)
    j = np.clip(np.floor(np.sum(rel * FACE_V[face], -1) * t), 0, t - 1).astype(np.int64)
    return face * t * t + j * t + i


@functools.lru_cache(maxsize=16)
def _permutations(t: int) -> np.ndarray:
    pos, normal, _ = _centres(t)
    out = []
    for r in range(4):
        out.append(locate(rotate_points(pos, r), t, rotate_directions(normal, r)))
    perms = np.stack(out)
    for r in range(4):
        if len(np.unique(perms[r])) != len(pos):
            raise AssertionError("a block turn is not a texel permutation")
    return perms


def rotation_permutation(t: int, turns: int) -> np.ndarray:
    """(n,) texel permutation of a turn: texel c of the block goes to texel ``perm[c]``."""
    return _permutations(int(t))[int(turns) % 4].copy()


def rotate_pattern(values, t: int, turns: int, axis: int = 0):
    """A per-texel array (texels along ``axis``) of a block, turned ``turns`` times:
    ``out[perm[c]] = values[c]``. NumPy in, NumPy out; JAX arrays use the same permutation."""
    perm = rotation_permutation(t, turns)
    inv = np.argsort(perm)
    return np.take(values, inv, axis=axis)


def exit_face(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """Where rays from inside (or on the boundary of) the unit block leave it: (N,) face index
    (0 floor, 1 ceiling, 2 + k side k) and (N, 3) exit points (slab method)."""
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.where(d > 0, (1.0 - o) / d, np.where(d < 0, -o / d, np.inf))
    axis = np.argmin(t_hi, axis=-1)
    tmin = np.take_along_axis(t_hi, axis[:, None], -1)[:, 0]
    pos = d[np.arange(len(d)), axis] > 0
    # axis 0: +x side 0 / -x side 2; axis 1: ceiling / floor; axis 2: +z side 1 / -z side 3
    face = np.where(axis == 1, np.where(pos, 1, 0),
                    np.where(axis == 0, np.where(pos, 2, 4), np.where(pos, 3, 5)))
    return face, o + tmin[:, None] * d


class Block(NamedTuple):
    """One cell of a layout: grid cell (i, j), dictionary type name, turns from the canonical
    block, and its missing sides in the layout's frame."""

    cell: tuple[int, int]
    kind: str
    turns: int
    open_sides: tuple[int, ...]


def _kind_of(open_sides: Sequence[int]) -> tuple[str, int]:
    want = set(open_sides)
    for name, canon in DICTIONARY.items():
        for r in range(4):
            if {(s + r) % 4 for s in canon} == want:
                return name, r
    raise AssertionError(f"no dictionary block has open sides {sorted(want)}")


class Layout(NamedTuple):
    """Grid cells, the open edges between them (each edge a pair of 4-adjacent cells) and
    ``exterior`` openings: (cell, side) pairs open onto the outside (a door to the sky, the open
    front of a Cornell box), through which light leaves and nothing returns."""

    cells: tuple[tuple[int, int], ...]
    edges: tuple[tuple[tuple[int, int], tuple[int, int]], ...]
    exterior: tuple[tuple[tuple[int, int], int], ...] = ()

    @classmethod
    def create(cls, cells, edges, exterior=()) -> "Layout":
        """Check and normalise: cells unique, edges between 4-adjacent cells of the layout,
        exterior openings on sides that face no cell of the layout."""
        cells = tuple(sorted({(int(c[0]), int(c[1])) for c in cells}))
        if not cells:
            raise ValueError("a layout needs at least one cell")
        cs = set(cells)
        norm = set()
        for a, b in edges:
            a, b = (int(a[0]), int(a[1])), (int(b[0]), int(b[1]))
            if a not in cs or b not in cs:
                raise ValueError(f"layout edge {a}-{b} names a cell that is not in the layout")
            if abs(a[0] - b[0]) + abs(a[1] - b[1]) != 1:
                raise ValueError(f"layout edge {a}-{b} joins cells that are not 4-adjacent")
            norm.add((min(a, b), max(a, b)))
        ext = set()
        for c, side in exterior:
            c, side = (int(c[0]), int(c[1])), int(side)
            if c not in cs or side not in range(4):
                raise ValueError(f"exterior opening ({c}, {side}): the cell must be in the layout and the side in 0-3")
            di, dj = SIDE_STEPS[side]
            if (c[0] + di, c[1] + dj) in cs:
                raise ValueError(f"exterior opening ({c}, {side}) faces a cell of the layout: use an edge")
            ext.add((c, side))
        return cls(cells, tuple(sorted(norm)), tuple(sorted(ext)))

    def open_sides(self, cell) -> tuple[int, ...]:
        """Sides of ``cell`` that open onto a connected neighbour or the outside."""
        edges, ext = set(self.edges), set(self.exterior)
        out = []
        for k, (di, dj) in enumerate(SIDE_STEPS):
            nb = (cell[0] + di, cell[1] + dj)
            if (min(cell, nb), max(cell, nb)) in edges or (tuple(cell), k) in ext:
                out.append(k)
        return tuple(out)

    @property
    def blocks(self) -> tuple[Block, ...]:
        """Each cell's block: dictionary type and turns (``_kind_of``)."""
        out = []
        for c in self.cells:
            sides = self.open_sides(c)
            kind, turns = _kind_of(sides)
            out.append(Block(c, kind, turns, sides))
        return tuple(out)

    def neighbour(self, index: int, side: int) -> int | None:
        """Index of the block across ``side`` of block ``index`` if that side is open."""
        c = self.cells[index]
        di, dj = SIDE_STEPS[side]
        nb = (c[0] + di, c[1] + dj)
        if (min(c, nb), max(c, nb)) not in set(self.edges):
            return None
        return self.cells.index(nb)

    def as_dict(self) -> dict:
        """JSON-able form (scene descriptions hash it); ``exterior`` only when there is one."""
        out = {"cells": [list(c) for c in self.cells], "edges": [[list(a), list(b)] for a, b in self.edges]}
        if self.exterior:
            out["exterior"] = [[list(c), s] for c, s in self.exterior]
        return out

    def has_cycle(self) -> bool:
        """Whether the open edges contain a cycle (edges >= cells in some connected component)."""
        parent = {c: c for c in self.cells}

        def find(c):
            while parent[c] != c:
                parent[c] = parent[parent[c]]
                c = parent[c]
            return c

        for a, b in self.edges:
            ra, rb = find(a), find(b)
            if ra == rb:
                return True
            parent[ra] = rb
        return False


def layout_from_dict(d) -> Layout:
    """``Layout`` from ``as_dict`` output (or a Layout)."""
    if isinstance(d, Layout):
        return d
    if not isinstance(d, dict) or not {"cells", "edges"} <= set(d) <= {"cells", "edges", "exterior"}:
        raise ValueError("a layout is {'cells': [[i, j], ...], 'edges': [[[i, j], [k, l]], ...]} with optional "
                         f"'exterior': [[[i, j], side], ...], got {d!r}")
    return Layout.create(d["cells"], d["edges"], d.get("exterior", ()))


def corridor(n: int) -> Layout:
    """``n`` blocks in a straight line along x."""
    cells = [(i, 0) for i in range(int(n))]
    return Layout.create(cells, list(zip(cells[:-1], cells[1:])))


def grid(w: int, h: int) -> Layout:
    """A w x h grid with every neighbour connected (cycles everywhere)."""
    cells = [(i, j) for i in range(int(w)) for j in range(int(h))]
    edges = [((i, j), (i + 1, j)) for i in range(w - 1) for j in range(h)]
    edges += [((i, j), (i, j + 1)) for i in range(w) for j in range(h - 1)]
    return Layout.create(cells, edges)


def random_maze(n: int, *, seed: int = 0, extra_edges: int = 0) -> Layout:
    """A random tree of ``n`` cells grown on the grid (random-neighbour growth), plus
    ``extra_edges`` edges between adjacent cells of the tree (each closes a cycle)."""
    rng = np.random.default_rng(seed)
    cells = [(0, 0)]
    edges = []
    cs = {(0, 0)}
    while len(cells) < n:
        c = cells[rng.integers(len(cells))]
        di, dj = SIDE_STEPS[rng.integers(4)]
        nb = (c[0] + di, c[1] + dj)
        if nb in cs:
            continue
        cells.append(nb)
        cs.add(nb)
        edges.append((c, nb))
    have = {(min(a, b), max(a, b)) for a, b in edges}
    extra = [(c, (c[0] + di, c[1] + dj)) for c in cells for di, dj in SIDE_STEPS[:2]
             if (c[0] + di, c[1] + dj) in cs and (c, (c[0] + di, c[1] + dj)) not in have]
    for k in rng.permutation(len(extra))[:int(extra_edges)]:
        edges.append(extra[k])
    return Layout.create(cells, edges)


def texel_albedo(layout: Layout, t: int, albedo: dict) -> np.ndarray:
    """(B, n, 3) albedo of every texel of every block (missing faces 0): ``albedo["floor"]``,
    ``albedo["ceiling"]`` and the wall palette ``albedo["walls"]`` (wall k of block b, in the
    layout's frame, takes palette entry (b + k) mod len)."""
    n = texel_count(t)
    out = np.zeros((len(layout.cells), n, 3), np.float64)
    palette = np.asarray(albedo["walls"], np.float64).reshape(-1, 3)
    for b, blk in enumerate(layout.blocks):
        per_face = [np.asarray(albedo["floor"], np.float64), np.asarray(albedo["ceiling"], np.float64)]
        for k in range(4):
            per_face.append(np.zeros(3) if k in blk.open_sides else palette[(b + k) % len(palette)])
        out[b] = np.repeat(np.stack(per_face), t * t, axis=0)
    return out
