"""Textured indoor room for the RGB-D renderer: planar textured quads built procedurally.

The room is the simulator's :class:`asgp_ros.sim.world.Room` (walls, furniture band, floor
surfaces). Everything is generated from a seed (no downloaded assets):

* floor: ``tile`` (0.30 m ceramic tiles with grout, per-tile shade and speckle: rich
  texture) or ``carpet`` (fine low-contrast fibre noise: feature-poor), per the room's
  surface map;
* walls: painted plaster with posters, doors, skirting boards and light switches, except
  for a *blank stretch* (plain paint, nothing in front of it) on the +y wall;
* furniture-like boxes (shelves with books, cabinets, tables) standing in the furniture
  band along the walls, never in front of the blank stretch;
* lighting baked into the textures: a smooth fall-off plus, in ``poor`` scenes, a dim zone
  (the rectangle ``dim_zone`` around the blank stretch, soft edges) where the image is at
  about a third of the brightness.

``preset="rich"`` is a tiled, well-lit room; ``preset="poor"`` has a carpet floor, a
second blank wall (-y side) and the dim zone.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from asgp_ros.sim.world import Room, room_for_surface

PRESETS = ("rich", "poor")


@dataclass
class Quad:
    """A textured planar rectangle: points origin + a*u + b*v for a, b in [0, 1].

    Attributes:
        origin: corner [3] in the world frame (m); texture pixel (0, 0).
        u: edge [3] along the texture columns (m); v: edge [3] along the texture rows (m).
        texture: [h, w, 3] uint8 BGR, lighting baked in.
        name: for debugging.
        mips: texture pyramid, mips[0] = texture (filled by :func:`_finish`).
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    texture: np.ndarray
    name: str = ""
    mips: list[np.ndarray] = field(default_factory=list)

    @property
    def normal(self) -> np.ndarray:
        """Unit normal [3] = u x v / |u x v| (the visible side)."""
        n = np.cross(self.u, self.v)
        unit: np.ndarray = n / np.linalg.norm(n)
        return unit

    @property
    def corners(self) -> np.ndarray:
        """Corners [4, 3] in order origin, +u, +u+v, +v."""
        o, u, v = self.origin, self.u, self.v
        return np.array([o, o + u, o + u + v, o + v])


@dataclass
class Scene:
    """The quads of a room and the facts tests need about it.

    Attributes:
        quads: list of :class:`Quad`.
        room: the simulator room.
        blank_wall: (x0, x1, y) of the blank stretch on the +y wall (m).
        dim_zone: (x0, x1, y0, y1) of the dim area (m), None when the light is even.
    """

    quads: list[Quad]
    room: Room
    blank_wall: tuple[float, float, float]
    dim_zone: tuple[float, float, float, float] | None


def _rng(seed: int, salt: int) -> np.random.Generator:
    return np.random.default_rng([seed, salt])


def _noise(rng: np.random.Generator, h: int, w: int, scale: float, sigma: float) -> np.ndarray:
    """Smooth noise [h, w] float32 of std about sigma with features of ``scale`` pixels."""
    sh, sw = max(2, int(h / scale)), max(2, int(w / scale))
    small = rng.standard_normal((sh, sw)).astype(np.float32)
    out: np.ndarray = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC) * sigma
    return out


def _tile_texture(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    tile = 0.30 * ppm
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    ix, iy = (xs // tile).astype(np.int32), (ys // tile).astype(np.int32)
    shades = rng.uniform(-28, 28, size=(int(h / tile) + 2, int(w / tile) + 2)).astype(np.float32)
    base = np.array([190, 196, 200], np.float32)  # BGR light grey-beige
    img: np.ndarray = base[None, None, :] + shades[iy, ix][..., None]
    img += rng.normal(0, 14, size=(h, w, 1)).astype(np.float32)  # speckle
    img += _noise(rng, h, w, 6, 14)[..., None]
    grout = ((xs % tile) < 0.012 * ppm) | ((ys % tile) < 0.012 * ppm)
    img[grout] = (95, 100, 105)
    return img


def _carpet_texture(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    base = np.array([110, 100, 140], np.float32)
    fibre: np.ndarray = rng.normal(0, 9, size=(h, w)).astype(np.float32)
    fibre = cv2.GaussianBlur(fibre, (0, 0), 1.2)
    # loop-pile mottling: low-contrast blobs a few centimetres across
    img: np.ndarray = (base[None, None, :] + fibre[..., None] + _noise(rng, h, w, 5, 9)[..., None]
                       + _noise(rng, h, w, 80, 3)[..., None])
    return img


def _paint(rng: np.random.Generator, w: int, h: int, colour: tuple[float, float, float]
           ) -> np.ndarray:
    img = np.empty((h, w, 3), np.float32)
    img[:] = colour
    img += _noise(rng, h, w, 150, 1.5)[..., None]
    return img


def _poster(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A poster [h, w, 3] float32: coloured blobs, stripes, a title block and text lines."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = rng.uniform(40, 230, size=3)
    for _ in range(rng.integers(4, 10)):
        c = tuple(float(x) for x in rng.uniform(0, 255, 3))
        kind = rng.integers(0, 3)
        x0, y0 = int(rng.integers(0, w)), int(rng.integers(0, h))
        if kind == 0:
            cv2.circle(img, (x0, y0), int(rng.integers(4, max(5, w // 4))), c, -1)
        elif kind == 1:
            cv2.rectangle(img, (x0, y0), (x0 + int(rng.integers(5, w // 2 + 6)),
                                          y0 + int(rng.integers(5, h // 3 + 6))), c, -1)
        else:
            pts = rng.integers(0, [w, h], size=(3, 2)).astype(np.int32)
            cv2.fillConvexPoly(img, pts, c)
    for k in range(int(rng.integers(3, 8))):  # text lines
        y = int(h * 0.65) + k * max(3, h // 25)
        if y >= h - 2:
            break
        x = 3
        while x < w - 6:
            wl = int(rng.integers(3, 12))
            cv2.rectangle(img, (x, y), (min(w - 3, x + wl), y + max(1, h // 60)), (20, 20, 20), -1)
            x += wl + int(rng.integers(2, 5))
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), (30, 30, 30), 2)
    return img


def _books(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    """Shelf front [h, w, 3]: wooden frame, shelves of books of random widths and colours."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = (60, 90, 130)  # wood
    img += _noise(rng, h, w, 4, 10)[..., None]
    shelf_h = int(0.38 * ppm)
    board = max(2, int(0.025 * ppm))
    for y0 in range(board, h - board, shelf_h):
        x = board
        while x < w - board:
            bw = int(rng.uniform(0.02, 0.06) * ppm)
            bh = int(rng.uniform(0.6, 0.95) * (shelf_h - board))
            c = tuple(float(v) for v in rng.uniform(20, 235, 3))
            y1 = min(h - board, y0 + shelf_h - board)
            cv2.rectangle(img, (x, y1 - bh), (min(w - board, x + bw), y1), c, -1)
            x += bw + int(rng.integers(0, 3))
        cv2.rectangle(img, (0, min(h - 1, y0 + shelf_h - board)),
                      (w - 1, min(h - 1, y0 + shelf_h)),
                      (40, 70, 110), -1)
    return img


def _wood(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    img = np.empty((h, w, 3), np.float32)
    img[:] = rng.uniform([40, 70, 100], [90, 120, 170])
    grain = _noise(rng, h, max(2, w // 8), 2, 12)
    img += cv2.resize(grain, (w, h))[..., None]
    img += rng.normal(0, 6, size=(h, w, 1)).astype(np.float32)
    return img


def _finish(q: Quad, light: Callable[[np.ndarray], np.ndarray]) -> Quad:
    """Bake lighting (callable world xyz [..., 3] -> gain) and build the mip pyramid."""
    h, w = q.texture.shape[:2]
    gh, gw = max(2, h // 8), max(2, w // 8)
    a = (np.arange(gw) + 0.5) / gw
    b = (np.arange(gh) + 0.5) / gh
    pts = q.origin + a[None, :, None] * q.u + b[:, None, None] * q.v  # [gh, gw, 3]
    gain = cv2.resize(light(pts).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    tex = np.clip(q.texture.astype(np.float32) * gain[..., None], 0, 255).astype(np.uint8)
    q.texture = tex
    q.mips = [tex]
    while min(q.mips[-1].shape[:2]) > 16 and len(q.mips) < 6:
        q.mips.append(cv2.pyrDown(q.mips[-1]))
    return q


def _wall_quad(p0: Sequence[float], p1: Sequence[float], height: float, texture: np.ndarray,
               name: str) -> Quad:
    """Vertical quad from floor point p0 to floor point p1 (texture rows top-down)."""
    a = np.array([p0[0], p0[1], height], float)
    b = np.array([p1[0], p1[1], height], float)
    return Quad(origin=a, u=b - a, v=np.array([0.0, 0.0, -height]), texture=texture,
                name=name)


def build_scene(room: Room | None = None, preset: str = "rich", seed: int = 0,
                wall_ppm: float = 120.0, floor_ppm: float = 160.0,
                ceiling: bool = False) -> Scene:
    """Build the textured room.

    Args:
        room: the simulator room; default ``room_for_surface("tile")`` for ``"rich"`` and
            ``room_for_surface("carpet")`` for ``"poor"``.
        preset: ``"rich"`` or ``"poor"`` (see module docstring).
        seed: texture and furniture seed.
        wall_ppm, floor_ppm: texture resolution, pixels per metre.
        ceiling: add a plain ceiling.
    Returns:
        the :class:`Scene`.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown scene preset {preset!r}; expected one of {PRESETS}")
    if room is None:
        room = room_for_surface("tile" if preset == "rich" else "carpet")
    x0, x1, y0, y1 = room.x_min, room.x_max, room.y_min, room.y_max
    H = room.wall_height
    poor = preset == "poor"
    cx, cy = room.centre
    dim_zone = (x0 + 1.5, x1 - 3.5, cy + 1.5, y1 + 1.0) if poor else None
    # blank stretch on the +y wall, centred on x = -1, 5 m long
    blank = (-3.5, 1.5, y1)

    quads: list[Quad] = [_floor_quad(room, seed, floor_ppm)]
    walls = [  # (name, p0, p1) traversed so that u x v points into the room
        ("wall_-x", (x0, y0), (x0, y1)),
        ("wall_+y", (x0, y1), (x1, y1)),
        ("wall_+x", (x1, y1), (x1, y0)),
        ("wall_-y", (x1, y0), (x0, y0)),
    ]
    for k, (name, p0, p1) in enumerate(walls):
        quads.extend(_wall_and_furniture(room, k, name, p0, p1, seed, wall_ppm, blank, poor))
    if ceiling:
        rng = _rng(seed, 30)
        cw, ch = int((x1 - x0) * 20), int((y1 - y0) * 20)
        quads.append(Quad(origin=np.array([x0, y0, H]), u=np.array([x1 - x0, 0.0, 0.0]),
                          v=np.array([0.0, y1 - y0, 0.0]),
                          texture=_paint(rng, cw, ch, (240, 240, 240)), name="ceiling"))
    inside = np.array([cx, cy, 0.5 * H])
    room_faces = {"floor", "ceiling"} | {name for name, _, _ in walls}
    light = _lighting(room, dim_zone)
    quads = [_finish(_face(q, inside) if q.name in room_faces else q, light) for q in quads]
    return Scene(quads=quads, room=room, blank_wall=blank, dim_zone=dim_zone)


def _lighting(room: Room, dim_zone: tuple[float, float, float, float] | None
              ) -> Callable[[np.ndarray], np.ndarray]:
    """The light factor at points p [..., 3]: ceiling lights over the centre, a gentle
    fall-off with distance, floor to ceiling, and 70 % darker in ``dim_zone``."""
    cx, cy = room.centre
    H = room.wall_height

    def light(p: np.ndarray) -> np.ndarray:
        # ceiling lights over the centre: gentle fall-off with distance, floor to ceiling
        r = np.hypot(p[..., 0] - cx, p[..., 1] - cy)
        g = 1.0 - 0.25 * np.clip(r / 7.0, 0.0, 1.0) + 0.05 * (p[..., 2] / H)
        if dim_zone is not None:
            zx0, zx1, zy0, zy1 = dim_zone

            def inside(a: np.ndarray, lo: float, hi: float) -> np.ndarray:
                # soft indicator of lo < a < hi, 0.3 m edges
                return 1.0 / ((1.0 + np.exp(-(a - lo) / 0.3)) * (1.0 + np.exp((a - hi) / 0.3)))

            g = g * (1.0 - 0.7 * inside(p[..., 0], zx0, zx1) * inside(p[..., 1], zy0, zy1))
        return g

    return light


def _floor_quad(room: Room, seed: int, floor_ppm: float) -> Quad:
    """The floor: tile or carpet texture by the room's base surface and its patches."""
    x0, x1, y0, y1 = room.x_min, room.x_max, room.y_min, room.y_max
    fw, fh = int((x1 - x0) * floor_ppm), int((y1 - y0) * floor_ppm)
    rng = _rng(seed, 1)
    tile = _tile_texture(rng, fw, fh, floor_ppm)
    carpet = _carpet_texture(rng, fw, fh)
    # texture row r is y = y1 - r / ppm (origin at (x0, y1)), column c is x = x0 + c / ppm
    xs = x0 + (np.arange(fw) + 0.5) / floor_ppm
    ys = y1 - (np.arange(fh) + 0.5) / floor_ppm
    is_carpet = np.full((fh, fw), room.base_surface == "carpet")
    for patch in room.patches:
        m = ((ys[:, None] >= patch.y_min) & (ys[:, None] <= patch.y_max)
             & (xs[None, :] >= patch.x_min) & (xs[None, :] <= patch.x_max))
        is_carpet[m] = patch.surface == "carpet"
    floor_tex = np.where(is_carpet[..., None], carpet, tile)
    return Quad(origin=np.array([x0, y1, 0.0]), u=np.array([x1 - x0, 0.0, 0.0]),
                v=np.array([0.0, y0 - y1, 0.0]), texture=floor_tex, name="floor")


#: Paint of the walls -x, +y, +x, -y.
_WALL_PAINT = [(205, 215, 222), (180, 200, 210), (200, 205, 190), (215, 210, 205)]


def _wall_and_furniture(room: Room, k: int, name: str, p0: tuple[float, float],
                        p1: tuple[float, float], seed: int, wall_ppm: float,
                        blank: tuple[float, float, float], poor: bool) -> list[Quad]:
    """Wall ``k`` from floor point p0 to p1 (visible side facing the room): paint,
    skirting board, posters, doors and light switches along it, and the furniture boxes
    standing in front of it; nothing on the blank stretches (``blank`` on the +y wall, and
    for the poor preset all of the -y wall)."""
    H = room.wall_height
    band = room.furniture_band
    cx, cy = room.centre
    rng = _rng(seed, 10 + k)
    length = math.hypot(p1[0] - p0[0], p1[1] - p0[1])
    w, h = int(length * wall_ppm), int(H * wall_ppm)
    img = _paint(rng, w, h, _WALL_PAINT[k])
    img[int((H - 0.12) * wall_ppm):] = (235, 235, 235)  # skirting board
    img[int((H - 0.12) * wall_ppm)] = (150, 150, 150)
    d = np.array(p1, float) - np.array(p0, float)
    d /= length

    def s_of_x(x: float) -> float:
        # arc-length coordinate along the wall of world x (for walls along x)
        return float((x - p0[0]) / d[0])

    blank_ranges: list[tuple[float, float]] = []
    if name == "wall_+y":
        lo, hi = sorted((s_of_x(blank[0]), s_of_x(blank[1])))
        blank_ranges.append((lo, hi))
    if poor and name == "wall_-y":
        blank_ranges.append((0.5, length - 0.5))

    def free(s_a: float, s_b: float) -> bool:
        return all(s_b < a or s_a > b for a, b in blank_ranges)

    furniture_spans: list[tuple[float, float]] = []
    s = 0.3
    while s < length - 0.8:
        item_w = float(rng.uniform(0.5, 1.3))
        if not free(s, s + item_w):
            s += 0.4
            continue
        kind = rng.integers(0, 5)
        if kind in (0, 1):  # poster
            ph = item_w * rng.uniform(0.6, 1.4)
            top = rng.uniform(0.35, 0.8)
            pw_px, ph_px = int(item_w * wall_ppm), int(ph * wall_ppm)
            r0, c0 = int(top * wall_ppm), int(s * wall_ppm)
            if r0 + ph_px < h - 0.5 * wall_ppm and c0 + pw_px < w:
                img[r0:r0 + ph_px, c0:c0 + pw_px] = _poster(rng, pw_px, ph_px)
        elif kind == 2:  # door
            dw = int(0.9 * wall_ppm)
            c0, r0 = int(s * wall_ppm), int((H - 2.05) * wall_ppm)
            if c0 + dw < w:
                img[r0:h - int(0.12 * wall_ppm), c0:c0 + dw] = _wood(rng, dw, h - r0 - int(
                    0.12 * wall_ppm))
                cv2.rectangle(img, (c0, r0), (c0 + dw, h), (40, 40, 40), 3)
                cv2.circle(img, (c0 + dw - int(0.1 * wall_ppm), r0 + int(1.05 * wall_ppm)),
                           int(0.03 * wall_ppm), (30, 160, 200), -1)
            item_w = 0.9
        else:  # furniture in front of the wall
            furniture_spans.append((s, item_w))
            r0 = int((H - 1.4) * wall_ppm)
            cv2.rectangle(img, (int(s * wall_ppm), r0), (int(s * wall_ppm) + 10, r0 + 16),
                          (235, 235, 235), -1)  # light switch next to it
        s += item_w + float(rng.uniform(0.2, 0.8))
    quads = [_wall_quad(p0, p1, H, img, name)]
    # furniture boxes for this wall
    inward = np.array([-d[1], d[0]])  # wall direction rotated by 90 deg ...
    if np.dot(inward, np.array([cx, cy]) - np.array(p0, float)) < 0:
        inward = -inward  # ... toward the room centre
    for s0, fw_m in furniture_spans:
        depth = float(rng.uniform(0.35, min(0.55, band)))
        height = float(rng.uniform(0.75, 1.9))
        a = np.array(p0, float) + d * s0 + inward * 0.02
        b = a + d * fw_m
        quads.extend(_box(rng, a, b, inward * depth, height, wall_ppm, f"{name}_box{s0:.1f}"))
    return quads


def _box(rng: np.random.Generator, a: Sequence[float] | np.ndarray,
         b: Sequence[float] | np.ndarray, depth_vec: Sequence[float] | np.ndarray,
         height: float, ppm: float, name: str) -> list[Quad]:
    """Front, top and the two side faces of a box standing on the floor against a wall.

    a, b: back corners on the floor along the wall [2]; depth_vec [2]: into the room.
    """
    a3 = np.array([a[0], a[1], 0.0])
    b3 = np.array([b[0], b[1], 0.0])
    dv = np.array([depth_vec[0], depth_vec[1], 0.0])
    up = np.array([0.0, 0.0, height])
    width = float(np.linalg.norm(b3 - a3))
    dep = float(np.linalg.norm(dv))
    fw, fh, dw = max(8, int(width * ppm)), max(8, int(height * ppm)), max(8, int(dep * ppm))
    shelf = rng.random() < 0.6
    front_tex = _books(rng, fw, fh, ppm) if shelf else _wood(rng, fw, fh)
    if not shelf:  # cabinet doors and handles
        for k in range(1, max(2, int(width / 0.45))):
            x = int(k * fw / max(2, int(width / 0.45)))
            cv2.line(front_tex, (x, 0), (x, fh - 1), (25, 35, 50), 2)
            cv2.rectangle(front_tex, (x - 8, fh // 3), (x - 5, fh // 3 + 18), (200, 200, 210), -1)
    fa, fb = a3 + dv, b3 + dv  # front bottom corners
    quads = [
        # front: rows top-down, columns from a to b; normal = (b-a) x (-up) points along dv
        Quad(origin=fa + up, u=fb - fa, v=-up, texture=front_tex, name=name + "_front"),
        Quad(origin=a3 + up, u=b3 - a3, v=dv, texture=_wood(rng, fw, dw), name=name + "_top"),
        Quad(origin=a3 + up, u=dv, v=-up, texture=_wood(rng, dw, fh), name=name + "_side_a"),
        Quad(origin=fb + up, u=-dv, v=-up, texture=_wood(rng, dw, fh), name=name + "_side_b"),
    ]
    # make every normal point away from the box centre (the visible side)
    centre = 0.5 * (a3 + b3) + 0.5 * dv + 0.5 * up
    return [_face(q, 2.0 * (q.origin + 0.5 * q.u + 0.5 * q.v) - centre) for q in quads]


def _face(q: Quad, toward: np.ndarray) -> Quad:
    """Orient q so that its normal points to the side of the point ``toward`` [3].

    Flipping mirrors both the geometry and the texture, so every world point keeps its texel.
    """
    mid = q.origin + 0.5 * q.u + 0.5 * q.v
    if np.dot(q.normal, np.asarray(toward, float) - mid) < 0:
        q.origin, q.u = q.origin + q.u, -q.u
        q.texture = np.ascontiguousarray(q.texture[:, ::-1])
    return q


# ----------------------------------------------------------------------------------------
# Chair drives for test sequences and benchmarks (ground truth for the renderer)


@dataclass(frozen=True)
class Drive:
    """A chair trajectory sampled at the camera rate.

    Attributes:
        t: [n] time (s); x, y, theta: [n] chair pose in the room (m, rad);
        v, omega: [n] true chair velocities (m/s, rad/s) at those times.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    v: np.ndarray
    omega: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def head(self, n: int) -> Drive:
        """The first n samples."""
        return Drive(*(a[:n] for a in (self.t, self.x, self.y, self.theta, self.v, self.omega)))


def segment_drive(start: tuple[float, float, float],
                  segments: list[tuple[float, float, float]], rate: float) -> Drive:
    """Unicycle drive through (v m/s, omega rad/s, duration s) segments, sampled at ``rate``.

    Integrated exactly per sample (constant-curvature arcs), so the twist between two
    samples is known in closed form.
    """
    if rate <= 0:
        raise ValueError(f"rate must be positive, got {rate}")
    dt = 1.0 / rate
    x, y, th = (float(c) for c in start)
    t = 0.0
    out = [[t, x, y, th, 0.0, 0.0]]
    for v, w, duration in segments:
        for _ in range(round(duration * rate)):
            if abs(w) > 1e-12:
                x += v / w * (math.sin(th + w * dt) - math.sin(th))
                y -= v / w * (math.cos(th + w * dt) - math.cos(th))
            else:
                x += v * dt * math.cos(th)
                y += v * dt * math.sin(th)
            th += w * dt
            t += dt
            out.append([t, x, y, th, v, w])
    a = np.array(out)
    a[0, 4:] = a[1, 4:] if len(a) > 1 else 0.0
    return Drive(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], a[:, 5])


def loop_drive(duration: float = 20.0, rate: float = 30.0, room: Room | None = None,
               speed: float = 0.55) -> Drive:
    """A smooth wavy ellipse around the room centre, clear of the furniture band.

    The ellipse (semi-axes 55 % / 45 % of the room's half sizes, radius modulated by
    +-8 % at three times the loop frequency) is run at a peak speed of about ``speed``;
    v and omega are the exact derivatives of the sampled path.
    """
    room = room or Room()
    cx, cy = room.centre
    a = 0.55 * 0.5 * (room.x_max - room.x_min)
    b = 0.45 * 0.5 * (room.y_max - room.y_min)
    rate_phi = speed / (1.08 * a)
    fine = 8
    t = np.arange(int(duration * rate * fine) + 2 * fine) / (rate * fine)
    phi = -0.5 * math.pi + rate_phi * t
    m = 1.0 + 0.08 * np.sin(3.0 * phi)
    x = cx + a * m * np.cos(phi)
    y = cy + b * m * np.sin(phi)
    dx, dy = np.gradient(x, t), np.gradient(y, t)
    theta = np.unwrap(np.arctan2(dy, dx))
    v = np.hypot(dx, dy)
    omega = np.gradient(theta, t)
    s = slice(0, int(duration * rate) * fine + 1, fine)
    return Drive(t[s], x[s], y[s], theta[s], v[s], omega[s])


def blank_wall_drive(rate: float = 30.0, room: Room | None = None,
                     scene: Scene | None = None) -> Drive:
    """Drive that turns the backward camera to the blank stretch of wall and away again.

    Start 1.5 m in front of the blank stretch (+y wall) heading +x, drive, turn in place
    until the camera faces the blank wall from about 1.1 m, stand, creep away, turn back
    to the textured room and drive on. Frames facing the wall have no texture.
    """
    room = room or Room()
    if scene is not None:
        bx0, bx1, _ = scene.blank_wall
        x_mid = 0.5 * (bx0 + bx1)
    else:
        x_mid = -1.0
    quarter = 0.5 * math.pi / 0.8
    segments = [(0.4, 0.0, 1.5), (0.0, -0.8, quarter), (0.0, 0.0, 1.5), (0.3, 0.0, 1.0),
                (0.0, 0.8, quarter), (0.5, 0.0, 2.0)]
    return segment_drive((x_mid - 0.6, room.y_max - 1.5, 0.0), segments, rate)
