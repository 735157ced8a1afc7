"""Indoor scenes built from textured primitives: the room shell, furniture, thin structures, lights.

World frame: z up, metres, the room spans [0, size] on each axis.  UVs are in texture repeats; most
surfaces project world coordinates (so textures keep their physical scale and line up across faces),
pictures and screens stretch one copy over the quad.  Quads are tessellated into cells of at most
``cell_m`` so that the baked shadows and ambient occlusion have somewhere to live.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rgs_warp.datasets.synthetic import textures as tx
from rgs_warp.datasets.synthetic.textures import CLAMP, MIRROR, REPEAT, srgb_to_linear
from rgs_warp.datasets.synthetic.trajectory import Trajectory, Waypoint


@dataclass(frozen=True)
class Material:
    texture: int
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    address: int = REPEAT
    emission: float = 0.0
    scale_m: float = 1.0  # metres per texture repeat for world-projected UVs


@dataclass(frozen=True)
class Light:
    position: tuple[float, float, float]
    colour: tuple[float, float, float]  # linear-light intensity (irradiance at 1 m)
    radius: float  # disc radius of the soft-shadow area light, metres
    facing: tuple[float, float, float] = (0.0, 0.0, 0.0)  # axis of a one-sided emitter; zero: omni


@dataclass
class Scene:
    name: str
    positions: np.ndarray  # (F, 3, 3) triangle corners
    uvs: np.ndarray  # (F, 3, 2)
    normals: np.ndarray  # (F, 3, 3) shading normals
    face_material: np.ndarray  # (F,)
    face_uv_per_m: np.ndarray  # (F,) texture repeats per metre (picks the mip level)
    materials: list[Material]
    textures: list[np.ndarray]
    lights: list[Light]
    ambient: tuple[float, float, float]
    room_size: np.ndarray  # (3,)
    obstacles: list[tuple[np.ndarray, np.ndarray]]  # furniture AABBs the camera must stay out of
    waypoints: list[Waypoint] = field(default_factory=list)

    def trajectory(self, seed: int = 0) -> Trajectory:
        return Trajectory(self.waypoints, seed=seed)

    def clearance_m(self, point) -> float:
        """Distance from ``point`` to the nearest wall, floor, ceiling or furniture box (negative inside)."""
        p = np.asarray(point, float)
        d = float(min(p.min(), (self.room_size - p).min()))
        for lo, hi in self.obstacles:
            outside = np.maximum(np.maximum(lo - p, p - hi), 0.0)
            inside = min((p - lo).min(), (hi - p).min())
            d = min(d, float(np.linalg.norm(outside)) if np.any(outside > 0) else -float(inside))
        return d


class SceneBuilder:
    def __init__(self, name: str, room_size, rng: np.random.Generator, cell_m: float = 0.15):
        self.name = name
        self.room_size = np.asarray(room_size, float)
        self.rng = rng
        self.cell_m = cell_m
        self._tris, self._uvs, self._normals, self._mats = [], [], [], []
        self.materials: list[Material] = []
        self.textures: list[np.ndarray] = []
        self.lights: list[Light] = []
        self.obstacles: list[tuple[np.ndarray, np.ndarray]] = []

    def material(self, image: np.ndarray, scale_m: float = 1.0, tint=(1.0, 1.0, 1.0), address=REPEAT, emission=0.0):
        self.textures.append(image.astype(np.float32))
        self.materials.append(Material(len(self.textures) - 1, tuple(tint), address, emission, scale_m))
        return len(self.materials) - 1

    def plain(self, srgb, amount: float = 0.012) -> int:
        """Painted, nearly textureless surface of the given sRGB colour."""
        return self.material(tx.plaster(self.rng, srgb_to_linear(srgb), amount), scale_m=2.0)

    def quad(self, origin, eu, ev, mat: int, fit: bool = False, cell_m: float | None = None):
        """Rectangle origin + s*eu + t*ev (s, t in [0, 1]) facing cross(eu, ev).

        ``fit`` stretches one texture copy over it (image top at t = 1); otherwise UVs are world
        coordinates along eu and ev over the material's ``scale_m``."""
        o, eu, ev = (np.asarray(a, float) for a in (origin, eu, ev))
        cell = cell_m or self.cell_m
        nu = max(1, int(np.ceil(np.linalg.norm(eu) / cell)))
        nv = max(1, int(np.ceil(np.linalg.norm(ev) / cell)))
        s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
        P = o + s[..., None] * eu + t[..., None] * ev
        if fit:
            UV = np.stack([s, 1.0 - t], -1)
        else:
            scale = self.materials[mat].scale_m
            UV = np.stack([P @ (eu / np.linalg.norm(eu)), -(P @ (ev / np.linalg.norm(ev)))], -1) / scale
        corners = [(0, 0), (1, 0), (1, 1), (0, 0), (1, 1), (0, 1)]
        idx_u = np.array([c[0] for c in corners])
        idx_v = np.array([c[1] for c in corners])
        iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
        iu, iv = iu.ravel()[:, None] + idx_u, iv.ravel()[:, None] + idx_v
        tris = P[iu, iv].reshape(-1, 3, 3)
        uvs = UV[iu, iv].reshape(-1, 3, 2)
        n = np.cross(eu, ev)
        n = n / np.linalg.norm(n)
        self._add(tris, uvs, np.broadcast_to(n, tris.shape), mat)

    def _add(self, tris, uvs, normals, mat):
        self._tris.append(np.asarray(tris, np.float32))
        self._uvs.append(np.asarray(uvs, np.float32))
        self._normals.append(np.asarray(normals, np.float32))
        self._mats.append(np.full(len(tris), mat, np.int32))

    def box(self, lo, hi, mat, obstacle: bool = True, faces: str = "xXyYzZ", fit: str = ""):
        """Axis-aligned box, outward faces.  ``mat`` is one material or a dict face -> material, faces
        named x/X (min/max x), y/Y, z/Z; ``fit`` names the faces that stretch one texture copy."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        dx, dy, dz = hi - lo
        spec = {
            "X": ((hi[0], lo[1], lo[2]), (0, dy, 0), (0, 0, dz)),
            "x": ((lo[0], hi[1], lo[2]), (0, -dy, 0), (0, 0, dz)),
            "Y": ((hi[0], hi[1], lo[2]), (-dx, 0, 0), (0, 0, dz)),
            "y": ((lo[0], lo[1], lo[2]), (dx, 0, 0), (0, 0, dz)),
            "Z": ((lo[0], lo[1], hi[2]), (dx, 0, 0), (0, dy, 0)),
            "z": ((lo[0], hi[1], lo[2]), (dx, 0, 0), (0, -dy, 0)),
        }
        for f in faces:
            m = mat[f] if isinstance(mat, dict) else mat
            self.quad(*spec[f], m, fit=f in fit)
        if obstacle:
            self.obstacles.append((lo, hi))

    def shell(self, floor: int, ceiling: int, walls: tuple[int, int, int, int]):
        """The room's inside: floor, ceiling and walls at x = 0, x = X, y = 0, y = Y, facing in (eu is
        the right-hand direction of someone facing the wall, so images are not mirrored)."""
        X, Y, Z = self.room_size
        self.quad((0, 0, 0), (X, 0, 0), (0, Y, 0), floor)
        self.quad((0, Y, Z), (X, 0, 0), (0, -Y, 0), ceiling)
        self.quad((0, 0, 0), (0, Y, 0), (0, 0, Z), walls[0])
        self.quad((X, Y, 0), (0, -Y, 0), (0, 0, Z), walls[1])
        self.quad((X, 0, 0), (-X, 0, 0), (0, 0, Z), walls[2])
        self.quad((0, Y, 0), (X, 0, 0), (0, 0, Z), walls[3])

    def cylinder(self, base, radius: float, height: float, mat: int, segments: int = 24, caps: bool = True):
        """Vertical cylinder, smooth-shaded side; an obstacle for the camera."""
        b = np.asarray(base, float)
        scale = self.materials[mat].scale_m
        a = np.linspace(0, 2 * np.pi, segments + 1)
        nz = max(1, int(np.ceil(height / self.cell_m)))
        z = np.linspace(0, height, nz + 1)
        A, Zg = np.meshgrid(a, z, indexing="ij")
        N = np.stack([np.cos(A), np.sin(A), np.zeros_like(A)], -1)
        P = b + radius * N + Zg[..., None] * np.array([0, 0, 1.0])
        UV = np.stack([A * radius, -(b[2] + Zg)], -1) / scale
        corners = [(0, 0), (1, 0), (1, 1), (0, 0), (1, 1), (0, 1)]
        ia, iz = np.meshgrid(np.arange(segments), np.arange(nz), indexing="ij")
        ia = ia.ravel()[:, None] + np.array([c[0] for c in corners])
        iz = iz.ravel()[:, None] + np.array([c[1] for c in corners])
        self._add(P[ia, iz].reshape(-1, 3, 3), UV[ia, iz].reshape(-1, 3, 2), N[ia, iz].reshape(-1, 3, 3), mat)
        if caps:
            i = np.arange(segments)
            for zc, up in ((height, 1.0), (0.0, -1.0)):
                ring = b + radius * N[:, 0] + np.array([0, 0, zc])
                first, second = (i, i + 1) if up > 0 else (i + 1, i)  # counter-clockwise seen from outside
                tris = np.stack([np.broadcast_to(b + [0, 0, zc], (segments, 3)), ring[first], ring[second]], 1)
                self._add(tris, tris[..., :2] / scale, np.broadcast_to([0, 0, up], tris.shape), mat)
        self.obstacles.append((b - [radius, radius, 0], b + [radius, radius, height]))

    # ---- composite furniture -------------------------------------------------------------------

    def table(self, lo_xy, hi_xy, height: float, top: int, legs: int, leg_w: float = 0.04, top_t: float = 0.035):
        (x0, y0), (x1, y1) = lo_xy, hi_xy
        self.box((x0, y0, height - top_t), (x1, y1, height), top)
        for x in (x0 + 0.03, x1 - 0.03 - leg_w):
            for y in (y0 + 0.03, y1 - 0.03 - leg_w):
                self.box((x, y, 0), (x + leg_w, y + leg_w, height - top_t), legs, faces="xXyY")

    def picture(self, wall: str, centre, size, image: int, frame: int, depth: float = 0.03, border: float = 0.04):
        """A framed picture hanging on wall x0/x1/y0/y1 (the room's walls), ``centre`` = (along, z)."""
        X, Y, _ = self.room_size
        w, h = size
        a, z = centre
        walls = {
            "x0": ((0.0, a, 0), (1, 0, 0)),
            "x1": ((X, a, 0), (-1, 0, 0)),
            "y0": ((a, 0.0, 0), (0, 1, 0)),
            "y1": ((a, Y, 0), (0, -1, 0)),
        }
        base, e_o = (np.asarray(v, float) for v in walls[wall])
        e_u = np.array([0, 0, 1.0])
        e_a = np.cross(-e_o, e_u)  # the viewer's right when facing the wall
        c = base + e_u * z
        self.quad(c - e_a * w / 2 - e_u * h / 2 + e_o * depth * 0.6, e_a * w, e_u * h, image, fit=True, cell_m=0.3)
        for da, du, la, lu in (
            (-(w + border) / 2, 0, border, h + 2 * border),
            ((w + border) / 2, 0, border, h + 2 * border),
            (0, -(h + border) / 2, w, border),
            (0, (h + border) / 2, w, border),
        ):
            p = c + e_a * da + e_u * du
            half = np.abs(e_a) * la / 2 + e_u * lu / 2
            lo = np.minimum(p - half, p - half + e_o * depth)
            hi = np.maximum(p + half, p + half + e_o * depth)
            self.box(lo, hi, frame, obstacle=False)

    def shelf(self, lo, hi, wood: int, books: int, levels: int = 4, board: float = 0.025):
        """Open bookcase against a wall (opening towards -y when its back is at hi[1])."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        self.box(lo, (lo[0] + board, hi[1], hi[2]), wood, obstacle=False)
        self.box((hi[0] - board, lo[1], lo[2]), hi, wood, obstacle=False)
        self.box((lo[0], hi[1] - board, lo[2]), hi, wood, obstacle=False, faces="yZz")
        zs = np.linspace(lo[2], hi[2] - board, levels + 1)
        for k, z in enumerate(zs):
            self.box((lo[0] + board, lo[1], z), (hi[0] - board, hi[1] - board, z + board), wood, obstacle=False)
            if k < levels:
                gap = zs[k + 1] - z - board
                depth = self.rng.uniform(0.55, 0.8) * (hi[1] - lo[1])
                self.box(
                    (lo[0] + board, hi[1] - board - depth, z + board),
                    (hi[0] - board, hi[1] - board, z + board + gap * 0.9),
                    {"y": books, "Z": wood, "x": wood, "X": wood},
                    obstacle=False,
                    faces="yZxX",
                )
        self.obstacles.append((lo, hi))

    def light(self, position, colour, radius: float, panel: int | None = None, panel_size=(0.5, 0.5)):
        """A lamp; with a ``panel``, a ceiling light: an emissive panel flush with the ceiling and a
        downward-facing area light just below it (so the ceiling is lit only by the ambient term)."""
        facing = (0.0, 0.0, -1.0) if panel is not None else (0.0, 0.0, 0.0)
        self.lights.append(Light(tuple(position), tuple(colour), radius, facing))
        if panel is not None:
            x, y, _ = position
            w, d = panel_size
            z = self.room_size[2] - 0.004
            self.quad((x - w / 2, y + d / 2, z), (w, 0, 0), (0, -d, 0), panel, fit=True)

    def build(self, ambient, waypoints: list[Waypoint]) -> Scene:
        pos = np.concatenate(self._tris)
        uvs = np.concatenate(self._uvs)
        area_w = 0.5 * np.linalg.norm(np.cross(pos[:, 1] - pos[:, 0], pos[:, 2] - pos[:, 0]), axis=1)
        e1, e2 = uvs[:, 1] - uvs[:, 0], uvs[:, 2] - uvs[:, 0]
        area_uv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        return Scene(
            name=self.name,
            positions=pos,
            uvs=uvs,
            normals=np.concatenate(self._normals),
            face_material=np.concatenate(self._mats),
            face_uv_per_m=np.sqrt(area_uv / np.maximum(area_w, 1e-12)).astype(np.float32),
            materials=self.materials,
            textures=self.textures,
            lights=self.lights,
            ambient=tuple(ambient),
            room_size=self.room_size,
            obstacles=self.obstacles,
            waypoints=waypoints,
        )


def _lin(*srgb) -> tuple[float, float, float]:
    return tuple(float(c) for c in srgb_to_linear(np.array(srgb)))


def _room0(rng: np.random.Generator) -> Scene:
    """Living room: wood floor, a brick accent wall, wallpaper, sofa, coffee table, bookcase, TV."""
    b = SceneBuilder("room0", (6.0, 5.0, 2.7), rng)
    floor = b.material(tx.wood_planks(rng, _lin(0.62, 0.44, 0.27), _lin(0.36, 0.22, 0.12), planks=6), scale_m=1.5)
    ceiling = b.plain((0.88, 0.87, 0.85), 0.01)
    west = b.plain((0.80, 0.74, 0.62))
    east = b.material(tx.photo("brick", (512, 512), _lin(0.85, 0.55, 0.45)), scale_m=1.3, address=MIRROR)
    south = b.material(tx.wallpaper(rng, _lin(0.78, 0.76, 0.66), _lin(0.45, 0.52, 0.42)), scale_m=1.0)
    north = b.plain((0.70, 0.72, 0.74))
    b.shell(floor, ceiling, (west, east, south, north))

    frame_wood = b.material(tx.wood_planks(rng, _lin(0.35, 0.2, 0.1), _lin(0.2, 0.1, 0.05), planks=1), scale_m=0.5)
    white_frame = b.plain((0.9, 0.9, 0.88), 0.02)
    b.picture("x0", (2.5, 1.55), (1.1, 1.1), b.material(tx.photo("astronaut", (512, 512)), address=CLAMP), frame_wood)
    b.picture("y0", (2.6, 1.6), (0.9, 0.6), b.material(tx.photo("chelsea", (256, 512)), address=CLAMP), white_frame)
    # window onto a night sky: a picture with extra mullions (thin bars)
    b.picture(
        "y1",
        (3.6, 1.55),
        (1.4, 1.0),
        b.material(tx.photo("hubble_deep_field", (256, 512)), address=CLAMP),
        white_frame,
        depth=0.06,
    )
    b.box((3.58, 4.95, 1.05), (3.62, 5.0, 2.05), white_frame, obstacle=False)
    b.box((2.9, 4.95, 1.53), (4.3, 5.0, 1.57), white_frame, obstacle=False)
    door = b.material(tx.wood_planks(rng, _lin(0.55, 0.4, 0.28), _lin(0.4, 0.27, 0.17), planks=2), scale_m=0.9)
    b.box((4.6, 4.96, 0.0), (5.5, 5.0, 2.05), door, obstacle=False)

    rug = b.material(tx.rug(rng), address=CLAMP)
    b.quad((1.8, 1.2, 0.006), (2.2, 0, 0), (0, 1.5, 0), rug, fit=True, cell_m=0.15)
    sofa_fabric = b.material(tx.fabric(rng, _lin(0.25, 0.42, 0.48)), scale_m=0.35)
    b.box((1.5, 0.05, 0.0), (3.7, 0.95, 0.42), sofa_fabric)
    b.box((1.5, 0.05, 0.42), (3.7, 0.32, 0.88), sofa_fabric)
    b.box((1.5, 0.32, 0.42), (1.72, 0.95, 0.62), sofa_fabric)
    b.box((3.48, 0.32, 0.42), (3.7, 0.95, 0.62), sofa_fabric)
    table_top = b.material(tx.wood_planks(rng, _lin(0.5, 0.32, 0.18), _lin(0.3, 0.17, 0.08), planks=3), scale_m=1.0)
    metal = b.plain((0.15, 0.15, 0.16), 0.03)
    b.table((2.1, 1.6), (3.1, 2.25), 0.44, table_top, metal, leg_w=0.03)
    magazine = b.material(tx.photo("coffee", (256, 512)), address=CLAMP)
    b.quad((2.3, 1.75, 0.444), (0.42, 0, 0), (0, 0.28, 0), magazine, fit=True)

    books = b.material(tx.books(rng), scale_m=0.9)
    b.shelf((0.35, 4.62, 0.0), (1.65, 5.0, 2.0), frame_wood, books, levels=5)
    cabinet = b.material(tx.drawers(rng, _lin(0.85, 0.84, 0.8), n=2), scale_m=0.55)
    b.box(
        (5.5, 1.8, 0.0),
        (5.98, 3.4, 0.55),
        {"x": cabinet, "X": cabinet, "y": metal, "Y": metal, "Z": metal},
        faces="xXyYZ",
    )
    b.box((5.88, 1.95, 0.85), (5.95, 3.25, 1.65), metal)
    screen = b.material(tx.photo("rocket", (256, 512)), address=CLAMP)
    b.quad((5.875, 3.2, 0.9), (0, -1.2, 0), (0, 0, 0.7), screen, fit=True)

    lamp = b.plain((0.9, 0.85, 0.7), 0.02)
    b.cylinder((5.45, 4.45, 0.0), 0.16, 0.03, metal)
    b.cylinder((5.45, 4.45, 0.03), 0.014, 1.45, metal, caps=False)
    b.cylinder((5.45, 4.45, 1.42), 0.2, 0.3, lamp, caps=False)
    vase = b.material(tx.photo("gravel", (256, 256), _lin(0.75, 0.7, 0.6)), scale_m=0.6, address=MIRROR)
    b.cylinder((0.45, 0.5, 0.0), 0.17, 0.55, vase)
    b.cylinder((4.35, 0.55, 0.0), 0.025, 0.6, metal, caps=False)
    b.cylinder((4.35, 0.55, 0.6), 0.3, 0.03, table_top)

    panel = b.material(tx.plaster(rng, np.ones(3, np.float32), 0.0), address=CLAMP, emission=1.4)
    warm = np.asarray(_lin(1.0, 0.95, 0.85))
    b.light((2.0, 2.5, 2.6), warm * 5.5, 0.25, panel)
    b.light((4.3, 2.5, 2.6), warm * 5.5, 0.25, panel)
    b.light((5.45, 4.45, 1.55), np.asarray(_lin(1.0, 0.8, 0.55)) * 1.2, 0.12)

    waypoints = [
        Waypoint(0.0, (1.6, 2.5, 1.45), (6.0, 2.4, 1.0)),
        Waypoint(1.8, (1.7, 2.3, 1.45), (5.6, 0.4, 1.0)),
        Waypoint(3.2, (1.9, 2.2, 1.5), (2.9, 0.0, 1.0)),
        Waypoint(4.0, (2.0, 2.3, 1.5), (0.3, 0.6, 1.3), roll_deg=4.0),
        Waypoint(5.2, (2.3, 2.7, 1.55), (0.6, 5.0, 1.2)),
        Waypoint(6.4, (3.0, 3.0, 1.45), (3.6, 5.0, 1.3)),
        Waypoint(7.0, (3.1, 2.9, 1.45), (5.9, 4.0, 1.0), roll_deg=-3.0),
        Waypoint(8.4, (2.8, 2.5, 1.3), (5.9, 1.9, 0.4)),
        Waypoint(10.0, (1.7, 2.45, 1.45), (6.0, 2.45, 1.0)),
    ]
    return b.build(ambient=_lin(0.42, 0.41, 0.4), waypoints=waypoints)


def _office0(rng: np.random.Generator) -> Scene:
    """Office: carpet tiles, acoustic ceiling, concrete and painted walls, desks, monitors, chairs."""
    b = SceneBuilder("office0", (5.5, 4.5, 2.6), rng)
    floor = b.material(tx.carpet(rng, _lin(0.36, 0.4, 0.46)), scale_m=1.0)
    ceiling = b.material(tx.tiles(rng, _lin(0.86, 0.86, 0.84), _lin(0.6, 0.6, 0.6), n=2, jitter=0.02), scale_m=1.2)
    west = b.plain((0.86, 0.86, 0.84))
    east = b.plain((0.68, 0.76, 0.82))
    south = b.material(tx.photo("gravel", (512, 512), _lin(0.72, 0.72, 0.7)), scale_m=1.6, address=MIRROR)
    north = b.material(tx.wallpaper(rng, _lin(0.8, 0.8, 0.78), _lin(0.7, 0.72, 0.74), n=12), scale_m=1.2)
    b.shell(floor, ceiling, (west, east, south, north))

    alu = b.plain((0.7, 0.7, 0.72), 0.02)
    black = b.plain((0.08, 0.08, 0.09), 0.03)
    whiteboard = b.material(tx.ink_on_white("text", (256, 512)), address=CLAMP)
    b.picture("x0", (2.3, 1.45), (1.8, 0.9), whiteboard, alu, depth=0.025, border=0.025)
    for along, name, size in (
        (1.0, "immunohistochemistry", (0.7, 0.7)),
        (2.4, "camera", (0.6, 0.6)),
        (3.6, "coffee", (0.9, 0.6)),
    ):
        img = b.material(tx.photo(name, (256, 256) if size[0] == size[1] else (256, 512)), address=CLAMP)
        b.picture("x1", (along, 1.55), size, img, black)

    desk = b.material(tx.wood_planks(rng, _lin(0.78, 0.7, 0.58), _lin(0.66, 0.57, 0.45), planks=1), scale_m=1.4)
    keys = b.material(
        tx.tiles(rng, _lin(0.12, 0.12, 0.13), _lin(0.5, 0.5, 0.5), n=16, jitter=0.0, grout_w=0.2), scale_m=0.3
    )
    for x0, shot in ((0.5, "astronaut"), (3.0, "hubble_deep_field")):
        b.table((x0, 0.3), (x0 + 1.6, 1.05), 0.75, desk, alu, leg_w=0.035)
        xm = x0 + 0.8
        b.box((xm - 0.1, 0.45, 0.75), (xm + 0.1, 0.6, 0.77), black, obstacle=False)
        b.box((xm - 0.02, 0.5, 0.77), (xm + 0.02, 0.54, 0.95), black, obstacle=False)
        b.box((xm - 0.3, 0.5, 0.92), (xm + 0.3, 0.54, 1.28), black, obstacle=False)
        img = b.material(tx.photo(shot, (256, 512)), address=CLAMP)
        b.quad((xm + 0.28, 0.542, 0.94), (-0.56, 0, 0), (0, 0, 0.32), img, fit=True)
        b.box(
            (xm - 0.23, 0.68, 0.75),
            (xm + 0.23, 0.84, 0.77),
            {"Z": keys, "y": black, "Y": black, "x": black, "X": black},
            obstacle=False,
            faces="ZyYxX",
        )

    fabric = b.material(tx.fabric(rng, _lin(0.2, 0.2, 0.24)), scale_m=0.3)
    for cx, cy in ((1.35, 1.55), (3.9, 1.65)):
        b.cylinder((cx, cy, 0.0), 0.28, 0.05, black)
        b.cylinder((cx, cy, 0.05), 0.025, 0.38, alu, caps=False)
        b.box((cx - 0.24, cy - 0.24, 0.43), (cx + 0.24, cy + 0.24, 0.5), fabric)
        b.box((cx - 0.22, cy + 0.2, 0.52), (cx + 0.22, cy + 0.26, 0.95), fabric)

    cabinet = b.material(tx.drawers(rng, _lin(0.55, 0.58, 0.6), n=3), scale_m=1.0)
    b.box(
        (4.85, 0.25, 0.0),
        (5.45, 0.85, 1.0),
        {"x": cabinet, "X": alu, "y": alu, "Y": alu, "Z": alu},
        faces="xXyYZ",
        fit="x",
    )
    books = b.material(tx.books(rng), scale_m=0.9)
    b.shelf((2.4, 4.12, 0.0), (3.7, 4.5, 1.8), desk, books, levels=4)
    b.cylinder((1.5, 3.1, 0.0), 0.3, 0.03, black)
    b.cylinder((1.5, 3.1, 0.03), 0.04, 0.69, alu, caps=False)
    b.cylinder((1.5, 3.1, 0.72), 0.55, 0.03, desk)
    pot = b.material(tx.tiles(rng, _lin(0.62, 0.32, 0.2), _lin(0.5, 0.25, 0.15), n=8, jitter=0.04), scale_m=0.4)
    b.cylinder((5.05, 4.05, 0.0), 0.18, 0.36, pot)
    leaves = b.material(tx.photo("grass", (512, 512), _lin(0.35, 0.6, 0.25)), scale_m=0.5, address=MIRROR)
    b.cylinder((5.05, 4.05, 0.36), 0.3, 0.7, leaves)
    b.cylinder((0.35, 4.15, 0.0), 0.2, 0.02, black)
    b.cylinder((0.35, 4.15, 0.02), 0.015, 1.75, alu, caps=False)

    panel = b.material(tx.plaster(rng, np.ones(3, np.float32), 0.0), address=CLAMP, emission=1.6)
    cool = np.asarray(_lin(0.92, 0.96, 1.0), np.float32)
    b.light((1.6, 2.2, 2.52), cool * 5.0, 0.3, panel, (1.2, 0.3))
    b.light((3.9, 2.2, 2.52), cool * 5.0, 0.3, panel, (1.2, 0.3))

    waypoints = [
        Waypoint(0.0, (2.8, 2.6, 1.5), (2.8, 0.0, 0.9)),
        Waypoint(1.8, (2.4, 2.4, 1.5), (0.4, 0.4, 0.9)),
        Waypoint(3.2, (2.6, 2.2, 1.45), (0.0, 2.4, 1.4)),
        Waypoint(3.9, (2.7, 2.3, 1.45), (1.4, 4.5, 1.0), roll_deg=-4.0),
        Waypoint(5.4, (3.2, 2.6, 1.55), (3.1, 4.5, 1.0)),
        Waypoint(6.6, (3.6, 2.9, 1.5), (5.5, 3.8, 0.9)),
        Waypoint(7.3, (3.5, 2.8, 1.5), (5.5, 1.4, 1.4), roll_deg=3.0),
        Waypoint(8.6, (3.2, 2.4, 1.35), (3.8, 0.6, 0.6)),
        Waypoint(10.0, (2.9, 2.6, 1.5), (2.7, 0.0, 0.9)),
    ]
    return b.build(ambient=_lin(0.44, 0.45, 0.47), waypoints=waypoints)


SCENES: dict[str, Callable[[np.random.Generator], Scene]] = {"room0": _room0, "office0": _office0}


def build_scene(name: str, seed: int = 0) -> Scene:
    if name not in SCENES:
        raise KeyError(f"unknown synthetic scene {name!r}; available: {sorted(SCENES)}")
    return SCENES[name](np.random.default_rng(seed))
