"""Stick-figure previews of BVH motion (animated GIF or PNG filmstrip) and numeric motion stats.

The camera is orthographic and faces the character: BVH +Z (the character's forward) points at
the viewer, +X is the viewer's right (the character's left), Y is up. The "side" view looks from
the character's right, so forward is the viewer's right. With `face_camera` the whole clip is
turned once about Y so that the character's mean heading faces the camera (one angle per clip, so
turning during the clip stays visible). Axis limits come from the whole rendered range, so the
figure never jumps; a fading trail of the hands shows the gesture even in a still.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimgestor.bvh import BvhError, BvhMotion, Skeleton, forward_kinematics, read_bvh

VIEWS = ("front", "side")
COLORS = {"left": "#1f77b4", "right": "#d62728", "center": "#303030"}
FLOOR_COLOR = "#9a9a9a"
GIF_FPS = 15.0  # default preview rate: a 10 s clip at the default size stays well under 2 MB
TRAIL_S = 1.0  # how far back the hand trails reach in the GIF


@dataclass
class StickFigure:
    """World positions of joints and End Sites turned to face the camera, and how to draw them."""

    positions: np.ndarray  # (T, N, 3): the skeleton's joints, then its End Sites
    names: list[str]  # N names; End Sites are "<joint>_end"
    bones: list[tuple[int, int]]  # (parent, child) point indices
    thin: np.ndarray  # (B,) bool: finger bones
    sides: list[str]  # per bone: "left", "right" or "center"
    head: tuple[int, int] | None  # (head point, point above it) for the head circle
    trails: list[int]  # points whose recent path is drawn
    frame_time: float


def side_of(name: str) -> str:
    """"left", "right" or "center" from the usual naming schemes (LeftArm, L_Arm, arm.L, ...)."""
    if re.search(r"left", name, re.I) or re.search(r"(^|[_.:])L([A-Z_.0-9]|$)", name):
        return "left"
    if re.search(r"right", name, re.I) or re.search(r"(^|[_.:])R([A-Z_.0-9]|$)", name):
        return "right"
    return "center"


def find_hands(names: list[str]) -> list[int]:
    """Indices of the hand (or wrist) joints: LeftHand/RightHand, else names ending in hand/wrist."""
    exact = [names.index(n) for n in ("LeftHand", "RightHand") if n in names]
    if exact:
        return exact
    return [j for j, n in enumerate(names) if re.search(r"(hand|wrist)$", n, re.I) and side_of(n) != "center"]


def _with_end_sites(skeleton: Skeleton) -> tuple[Skeleton, list[int]]:
    """The skeleton with each End Site as an extra channel-less joint; returns it and the End Site parents."""
    ends = sorted(skeleton.end_sites)
    ext = Skeleton(
        names=skeleton.names + [f"{skeleton.names[j]}_end" for j in ends],
        parents=list(skeleton.parents) + ends,
        offsets=np.concatenate([skeleton.offsets, np.array([skeleton.end_sites[j] for j in ends]).reshape(-1, 3)]),
        channels=[list(c) for c in skeleton.channels] + [[] for _ in ends],
    )
    return ext, ends


def world_positions(motion: BvhMotion, end_sites: bool = True) -> tuple[np.ndarray, list[str], list[int]]:
    """(T, N, 3) positions of the joints (and End Sites appended), their names and parents."""
    sk = motion.skeleton
    if not end_sites or not sk.end_sites:
        return forward_kinematics(motion), list(sk.names), list(sk.parents)
    ext, ends = _with_end_sites(sk)
    T, E = motion.num_frames, len(ends)
    rot = np.concatenate([motion.rotations(), np.tile([1.0, 0.0, 0.0, 0.0], (T, E, 1))], axis=1)
    trans = np.concatenate([motion.translations(), np.broadcast_to(ext.offsets[sk.num_joints:], (T, E, 3))], axis=1)
    return forward_kinematics(ext, rot, trans), ext.names, ext.parents


def facing_yaw(positions: np.ndarray, names: list[str]) -> float:
    """Mean heading (radians about +Y, 0 = facing +Z) from left-minus-right vectors of the hips and shoulders."""
    pairs = [(f"Left{b}", f"Right{b}") for b in ("UpLeg", "Arm", "Shoulder", "Hip", "Thigh")]
    pairs = [(names.index(a), names.index(b)) for a, b in pairs if a in names and b in names]
    if not pairs:
        return 0.0
    left = sum((positions[:, a] - positions[:, b]).mean(0) for a, b in pairs)
    forward = np.array([-left[2], left[0]])  # (x, z) of left x up: a character with left = +X faces +Z
    return float(np.arctan2(forward[0], forward[1])) if np.hypot(*forward) > 1e-9 else 0.0


def _rotate_y(p: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = p.copy()
    out[..., 0] = c * p[..., 0] + s * p[..., 2]
    out[..., 2] = -s * p[..., 0] + c * p[..., 2]
    return out


def stick_figure(motion: BvhMotion, end_sites: bool = True, face_camera: bool = True,
                 trail_joints: tuple[str, ...] | None = None) -> StickFigure:
    """Forward kinematics and drawing roles (sides, finger bones, head, trails) for a motion."""
    pos, names, parents = world_positions(motion, end_sites)
    if face_camera:
        pos = _rotate_y(pos, -facing_yaw(pos, names))
    hands = find_hands(names)
    below_hand = np.zeros(len(names), bool)
    for j, p in enumerate(parents):  # parents precede children
        below_hand[j] = p >= 0 and (p in hands or below_hand[p])
    head = next((j for j, n in enumerate(names) if n.lower() == "head"), None)
    head = head if head is not None else next((j for j, n in enumerate(names) if n.lower().endswith("head")), None)
    tops = [k for k, p in enumerate(parents) if p == head and head is not None]
    # the head's longest child (its top, not an eye or jaw) sizes the head circle
    tip = max(tops, key=lambda k: np.linalg.norm(pos[0, k] - pos[0, head])) if tops else None
    bones = [(p, j) for j, p in enumerate(parents) if p >= 0 and not (p == head and j == tip)]
    if trail_joints is None:
        trails = [j for j in hands if names[j].lower().endswith("hand")] or hands
    else:
        missing = [n for n in trail_joints if n not in names]
        if missing:
            raise ValueError(f"trail joints not in the skeleton: {missing}")
        trails = [names.index(n) for n in trail_joints]
    return StickFigure(
        positions=pos, names=names, bones=bones,
        thin=np.array([bool(below_hand[j]) for _, j in bones]),
        sides=[side_of(names[j]) for _, j in bones],
        head=(head, tip) if head is not None and tip is not None else None,
        trails=trails, frame_time=motion.frame_time,
    )


def project(points: np.ndarray, view: str) -> np.ndarray:
    """(..., 3) camera-aligned points -> (..., 2) screen coordinates of an orthographic view."""
    if view == "front":
        return points[..., [0, 1]]
    if view == "side":
        return points[..., [2, 1]]
    raise ValueError(f"unknown view {view!r}; choose from {VIEWS}")


def nearness(points: np.ndarray, view: str) -> np.ndarray:
    """(..., 3) -> (...,) distance toward the camera of a view (larger is nearer)."""
    return points[..., 2] if view == "front" else -points[..., 0]


def _rgba(color: str, alpha: float) -> tuple:
    from matplotlib.colors import to_rgba

    return to_rgba(color, alpha)


class _ViewArtists:
    """The artists of one view on one axes, moved to any frame with update()."""

    def __init__(self, ax, figure: StickFigure, view: str, lines: slice, lw: float):
        from matplotlib.collections import LineCollection

        self.figure, self.view = figure, view
        fig = figure
        pts = project(fig.positions[lines], view)
        lo, hi = pts.reshape(-1, 2).min(0), pts.reshape(-1, 2).max(0)
        if fig.head is not None:  # leave room for the head circle
            hi[1] += self._head_radius(fig.positions[lines]).max()
        floor = lo[1]
        pad = 0.06 * max(hi[1] - lo[1], hi[0] - lo[0], 1e-6)
        lo, hi = lo - pad, hi + pad
        # Equal scale on both axes: widen the limits about their centre to the axes box's aspect.
        box = ax.get_position()
        box_aspect = (box.height * ax.figure.bbox.height) / max(box.width * ax.figure.bbox.width, 1e-6)
        span = hi - lo
        if span[1] / span[0] > box_aspect:
            half = 0.5 * span[1] / box_aspect
            lo[0], hi[0] = 0.5 * (lo[0] + hi[0]) - half, 0.5 * (lo[0] + hi[0]) + half
        else:
            half = 0.5 * span[0] * box_aspect
            lo[1], hi[1] = 0.5 * (lo[1] + hi[1]) - half, 0.5 * (lo[1] + hi[1]) + half
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_axis_off()
        ax.axhline(floor, color=FLOOR_COLOR, lw=1.2 * lw / 2.5, zorder=0)
        self.trails = [LineCollection([], linewidths=0.6 * lw, zorder=1) for _ in fig.trails]
        for t in self.trails:
            ax.add_collection(t)
        self.widths = np.where(fig.thin, 0.35 * lw, lw)
        self.colors = np.array([_rgba(COLORS[s], 1.0) for s in fig.sides]).reshape(-1, 4)
        self.bones = LineCollection([], capstyle="round", zorder=2)
        ax.add_collection(self.bones)
        (self.head,) = ax.plot([], [], color=COLORS["center"], lw=0.8 * lw, zorder=3)
        self.bone_index = np.array(fig.bones, dtype=int).reshape(-1, 2)

    def _head_radius(self, positions: np.ndarray) -> np.ndarray:
        h, t = self.figure.head
        return 0.75 * np.linalg.norm(positions[:, t] - positions[:, h], axis=-1)

    def update(self, frame: int, trail_from: int) -> None:
        fig = self.figure
        p = fig.positions[frame]
        ends = p[self.bone_index]  # (B, 2, 3)
        order = np.argsort(nearness(ends.mean(1), self.view), kind="stable")  # far bones first, near ones on top
        self.bones.set_segments(project(ends[order], self.view))
        self.bones.set_color(self.colors[order])
        self.bones.set_linewidth(self.widths[order])
        if fig.head is not None:
            h, t = fig.head
            centre = project(0.5 * (p[h] + p[t]), self.view)
            r = float(self._head_radius(p[None])[0])
            a = np.linspace(0, 2 * np.pi, 33)
            self.head.set_data(centre[0] + r * np.cos(a), centre[1] + r * np.sin(a))
        for coll, j in zip(self.trails, fig.trails):
            path = project(fig.positions[trail_from:frame + 1, j], self.view)
            segs = np.stack([path[:-1], path[1:]], axis=1) if len(path) > 1 else np.zeros((0, 2, 2))
            alpha = np.linspace(0.05, 0.7, len(segs)) if len(segs) else []
            coll.set_segments(segs)
            coll.set_color([_rgba(COLORS[side_of(fig.names[j])], a) for a in alpha])


def _frame_range(motion: BvhMotion, start_s: float, seconds: float | None) -> tuple[int, int]:
    first = int(round(start_s * motion.fps))
    if start_s < 0 or first >= motion.num_frames:
        raise ValueError(f"start {start_s:g} s is outside the clip ({motion.duration:.2f} s, {motion.num_frames} frames)")
    if seconds is not None and not seconds > 0:
        raise ValueError(f"seconds must be > 0, got {seconds:g}")
    last = motion.num_frames if seconds is None else min(motion.num_frames, first + max(1, int(round(seconds * motion.fps))))
    return first, last


def _new_figure(size: tuple[int, int]):
    # A bare Figure on an Agg canvas: no pyplot, so no GUI backend and no global state is touched.
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def gif_palette() -> np.ndarray:
    """A fixed (K, 3) uint8 palette: each drawing colour blended with white, and a grey ramp for text."""
    from matplotlib.colors import to_rgb

    rgb = [np.ones(3)]  # white first: the background (to_palette relies on it)
    for c in list(COLORS.values()):
        rgb += [a * np.array(to_rgb(c)) + (1 - a) for a in np.linspace(1 / 47, 1.0, 47)]
    rgb += [np.full(3, g) for g in np.linspace(0, 62 / 63, 63)]
    return (np.array(rgb) * 255).round().astype(np.uint8)


def to_palette(rgb: np.ndarray, palette: np.ndarray):
    """(H, W, 3) uint8 -> a "P" image, each colour mapped to its nearest palette entry (no dithering).

    Exact nearest colours (Pillow's palette lookup is approximate and turns white grey); line art
    has few distinct colours, so matching the unique ones is fast.
    """
    from PIL import Image

    packed = ((rgb[..., 0].astype(np.int32) << 16) | (rgb[..., 1].astype(np.int32) << 8) | rgb[..., 2]).reshape(-1)
    index = np.zeros(packed.size, np.uint8)  # entry 0 is white, the background
    drawn = np.flatnonzero(packed != 0xFFFFFF)
    uniq, inverse = np.unique(packed[drawn], return_inverse=True)
    cols = np.stack([(uniq >> 16) & 255, (uniq >> 8) & 255, uniq & 255], -1).astype(np.float32)
    index[drawn] = ((cols[:, None] - palette[None].astype(np.float32)) ** 2).sum(-1).argmin(1)[inverse.reshape(-1)]
    img = Image.fromarray(index.reshape(rgb.shape[:2]), "P")
    img.putpalette(palette.reshape(-1).tolist())
    return img


def render_gif(figure: StickFigure, out_path, first: int, last: int, fps: float, size, views, title) -> int:
    """Animated GIF of frames first..last-1, subsampled to about `fps`; returns the frame count."""
    step = max(1, int(round(1.0 / (figure.frame_time * fps))))
    frames = list(range(first, last, step))
    fig = _new_figure(size)
    spans = [np.ptp(project(figure.positions[first:last], v)[..., 0]) + 1e-6 for v in views]
    axes = fig.subplots(1, len(views), squeeze=False, gridspec_kw={"width_ratios": spans})[0]
    lw = 2.5 * size[1] / 400
    top = 0.9 if title else 0.94
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.02, top=top, wspace=0.05)
    artists = [_ViewArtists(ax, figure, v, slice(first, last), lw) for ax, v in zip(axes, views)]
    for ax, v in zip(axes, views):  # figure text: an axes title costs a tight-bbox pass on every draw
        box = ax.get_position()
        fig.text(box.x0 + box.width / 2, box.y1, v, ha="center", va="bottom", fontsize=8, color="#606060")
    if title:
        fig.suptitle(title, fontsize=10, y=0.995)
    clock = fig.text(0.99, 0.01, "", ha="right", va="bottom", fontsize=8, color="#606060")
    palette = gif_palette()
    images = []
    trail_n = int(round(TRAIL_S / figure.frame_time))
    for f in frames:
        for a in artists:
            a.update(f, max(first, f - trail_n))
        clock.set_text(f"{f * figure.frame_time:5.2f} s")
        fig.canvas.draw()
        images.append(to_palette(np.asarray(fig.canvas.buffer_rgba())[..., :3], palette))
    # GIF delays are whole centiseconds: round the cumulative clock so playback keeps real time.
    ticks = np.round(np.arange(len(frames) + 1) * step * figure.frame_time * 100).astype(int)
    images[0].save(out_path, format="GIF", save_all=True, append_images=images[1:],
                   duration=[int(d) * 10 for d in np.diff(ticks)], loop=0)
    return len(frames)


def render_filmstrip(figure: StickFigure, out_path, first: int, last: int, panels: int, size, views, title) -> int:
    """PNG of `panels` evenly spaced poses (columns) in each view (rows); returns the pose count."""
    frames = np.unique(np.round(np.linspace(first, last - 1, panels)).astype(int))
    fig = _new_figure(size)
    axes = fig.subplots(len(views), len(frames), squeeze=False)
    lw = 2.2 * size[1] / (300 * len(views))
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.86 if title else 0.93, wspace=0.02, hspace=0.04)
    prev = [first] + list(frames[:-1])
    for r, v in enumerate(views):
        for c, (f, p) in enumerate(zip(frames, prev)):
            _ViewArtists(axes[r, c], figure, v, slice(first, last), lw).update(int(f), int(p))
            if r == 0:
                axes[r, c].set_title(f"{f * figure.frame_time:.2f} s", fontsize=8, color="#606060", pad=2)
        axes[r, 0].text(0.0, 0.98, v, transform=axes[r, 0].transAxes, fontsize=7, color="#909090", va="top")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(out_path, dpi=100, facecolor="white")
    return len(frames)


def render_motion(motion: BvhMotion, out_path, fps: float | None = None, start_s: float = 0.0,
                  seconds: float | None = None, size: tuple[int, int] | None = None, views=VIEWS,
                  title: str | None = None, trail_joints: tuple[str, ...] | None = None, panels: int = 6,
                  end_sites: bool = True, face_camera: bool = True) -> int:
    """Write an animated .gif (at about `fps`, default 15) or a .png filmstrip of `panels` poses.

    `size` is (width, height) in pixels; `trail_joints` default to the hands. Returns the number of
    frames (GIF) or poses (PNG) drawn.
    """
    out_path = Path(out_path)
    kind = out_path.suffix.lower()
    if kind not in (".gif", ".png"):
        raise ValueError(f"{out_path}: output must be .gif (animation) or .png (filmstrip)")
    views = tuple(views)
    for v in views:
        project(np.zeros(3), v)  # validates the name
    if fps is not None and not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps:g}")
    first, last = _frame_range(motion, start_s, seconds)
    figure = stick_figure(motion, end_sites, face_camera, trail_joints)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    if kind == ".gif":
        size = size or (300 * len(views), 400)
        return render_gif(figure, out_path, first, last, fps or GIF_FPS, size, views, title)
    if panels < 1:
        raise ValueError(f"panels must be >= 1, got {panels}")
    size = size or (170 * panels, 290 * len(views) + (30 if title else 15))
    return render_filmstrip(figure, out_path, first, last, panels, size, views, title)


def motion_stats(motion: BvhMotion) -> dict:
    """Per-joint world position ranges, hand travel and joint speeds, in file units (and per second)."""
    sk = motion.skeleton
    if motion.num_frames == 0:
        raise ValueError("motion_stats: the motion has no frames")
    pos = forward_kinematics(motion)  # (T, J, 3)
    hands = find_hands(sk.names)
    rel = pos - pos[:, :1]  # relative to the root: gesture without travel
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=-1) * motion.fps  # (T - 1, J) units/s
    stats = {
        "frames": motion.num_frames,
        "fps": motion.fps,
        "duration_s": motion.duration,
        "joints": {n: {"min": pos[:, j].min(0).tolist(), "max": pos[:, j].max(0).tolist(),
                       "range": np.ptp(pos[:, j], axis=0).tolist()} for j, n in enumerate(sk.names)},
        # max distance of each hand from its mean position, in the world and relative to the root
        "hand_travel": {sk.names[j]: float(np.linalg.norm(pos[:, j] - pos[:, j].mean(0), axis=-1).max()) for j in hands},
        "hand_travel_rel_root": {sk.names[j]: float(np.linalg.norm(rel[:, j] - rel[:, j].mean(0), axis=-1).max())
                                 for j in hands},
        "max_joint_speed": 0.0, "max_joint_speed_joint": None, "max_joint_speed_time_s": None,
        # mocap has single-frame spikes (ZEGGS elbows reach 11 m/s for a frame): a robust companion
        "joint_speed_p99": float(np.percentile(speed.max(1), 99)) if len(speed) else 0.0,
        "mean_hand_speed": {sk.names[j]: float(speed[:, j].mean()) if len(speed) else 0.0 for j in hands},
    }
    if len(speed):
        t, j = np.unravel_index(int(np.argmax(speed)), speed.shape)
        stats.update(max_joint_speed=float(speed[t, j]), max_joint_speed_joint=sk.names[j],
                     max_joint_speed_time_s=float((t + 0.5) * motion.frame_time))
    return stats


# ---- CLI -----------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bvh", metavar="MOTION", help="input BVH file, or a BEAT2 / SMPL-X take (.npz)")
    p.add_argument("--out", required=True, metavar="OUT.gif|OUT.png",
                   help="OUT.gif (animation) or OUT.png (filmstrip of evenly spaced poses)")
    g = p.add_argument_group("what to render")
    g.add_argument("--start", type=float, default=0.0, metavar="S", help="first second to render")
    g.add_argument("--seconds", type=float, default=None, metavar="S",
                   help="how many seconds to render (default: to the end)")
    g.add_argument("--views", default=",".join(VIEWS), help="comma-separated views: front, side")
    g.add_argument("--panels", type=int, default=6, metavar="N", help="poses in a PNG filmstrip")
    g.add_argument("--no-face-camera", action="store_true",
                   help="keep the file's heading instead of turning it to the camera")
    g = p.add_argument_group("image")
    g.add_argument("--fps", type=float, default=None,
                   help=f"GIF frame rate; frames are subsampled (default: {GIF_FPS:g})")
    g.add_argument("--width", type=int, default=None, metavar="PX",
                   help="image width in pixels, with --height (default: sized to the views)")
    g.add_argument("--height", type=int, default=None, metavar="PX",
                   help="image height in pixels, with --width (default: sized to the views)")
    g.add_argument("--title", default=None, help="title (default: the file name)")


def main_from_args(args: argparse.Namespace) -> int:
    try:
        if Path(args.bvh).suffix.lower() == ".npz":  # a BEAT2 / SMPL-X take, on the generic SMPL-X skeleton
            from dimgestor.smplx import read_smplx

            motion = read_smplx(args.bvh)[0]
        else:
            motion = read_bvh(args.bvh)
        views = tuple(v.strip() for v in args.views.split(",") if v.strip())
        size = None
        if args.width is not None or args.height is not None:
            if args.width is None or args.height is None or args.width < 16 or args.height < 16:
                raise ValueError("--width and --height go together and must be >= 16 pixels")
            size = (args.width, args.height)
        n = render_motion(motion, args.out, fps=args.fps, start_s=args.start, seconds=args.seconds, size=size,
                          views=views, title=args.title if args.title is not None else Path(args.bvh).name,
                          panels=args.panels, face_camera=not args.no_face_camera)
    except (BvhError, ValueError, OSError) as e:  # as dimgestor_app.cli does, so the command also works on its own
        if os.environ.get("DIMGESTOR_DEBUG"):
            raise
        msg = f"{e.filename}: {e.strerror or e}" if isinstance(e, OSError) and e.filename else str(e)
        print(f"error: {msg}", file=sys.stderr)
        return 2
    what = "frames" if Path(args.out).suffix.lower() == ".gif" else "poses"
    print(f"wrote {args.out} ({n} {what})")
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the `render` subcommand to the `dimgestor` CLI."""
    from dimgestor.cli_help import examples

    p = subparsers.add_parser("render", help="stick-figure preview of a BVH file (GIF animation or PNG filmstrip)",
                              description=__doc__.split("\n\n")[0],
                              epilog=examples("dimgestor render motion.bvh --out motion.gif",
                                              "dimgestor render motion.bvh --out strip.png --panels 8 --views front",
                                              "dimgestor render motion.bvh --out clip.gif --start 2 --seconds 5 --fps 10"))
    add_arguments(p)
    p.set_defaults(func=main_from_args)
    return p
