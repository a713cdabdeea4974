"""An animation of a marionette trajectory (GIF or MP4), rendered headless with matplotlib.

Front (x-y) and side (z-y) orthographic views framed on what moves: the puppet's boxes and head
sphere, the strings (taut dark, slack orange), the bars, the chair and the ball, with the ground.
Two panels plot what the strings do to the device and the puppet over the whole run, with a cursor
at the frame's time: the reaction on each bar (the force ``live`` sends a device, before scaling)
and each string's tension (the magnitude of its tie force on the puppet), both autoscaled.

Fast: the figure is drawn once; each frame restores that background and draws only the artists
that move (blitting on the Agg canvas), then the RGB buffer goes to Pillow (GIF) or imageio-ffmpeg
(MP4). Exact timing: a GIF stores delays in 10 ms units, so frame ``k``'s delay is the difference
of the rounded cumulative times, ``round(100 (k+1) / fps) - round(100 k / fps)`` centiseconds
(15 fps: 70, 60, 70, 70, 60, … ms): the animation's length is the simulated time to within 5 ms.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from dmarionette.marionette.rollout import MarionetteTrajectory
from dmarionette.render.pyplot import headless_pyplot
from dmarionette.rotations import quat_to_matrix

__all__ = ["draw_chair", "frame_extent", "gif_delays_ms", "render_marionette_animation"]

_BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
_BOX_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
_BAR_HALF_LENGTH = 0.12  # [m], the bar drawn along its own x axis
_NAN = np.full((1, 3), np.nan)


def gif_delays_ms(count: int, fps: float) -> list[int]:
    """Per-frame GIF delays [ms], multiples of 10 ms, whose running sum stays within 5 ms of ``k / fps``."""
    edges = np.round(100.0 * np.arange(count + 1) / fps).astype(int)
    return [10 * int(d) for d in np.diff(edges)]


def body_polyline(trajectory: MarionetteTrajectory, f: int) -> np.ndarray:
    """The puppet's bodies at frame ``f`` as one polyline, pieces separated by NaN rows: box edges, sphere rings."""
    pieces = []
    for b, (shape, size) in enumerate(trajectory.body_shape):
        rotation = quat_to_matrix(trajectory.body_rot[f, b])
        centre = trajectory.body_pos[f, b]
        if shape == "box":
            corners = centre + (_BOX_CORNERS * 0.5 * np.asarray(size)) @ rotation.T
            for i, j in _BOX_EDGES:
                pieces += [corners[[i, j]], _NAN]
        else:
            angle = np.linspace(0, 2 * np.pi, 25)
            for ring in (np.stack([np.cos(angle), np.sin(angle), 0 * angle], 1),
                         np.stack([0 * angle, np.sin(angle), np.cos(angle)], 1)):
                pieces += [centre + (size[0] * ring) @ rotation.T, _NAN]
    return np.concatenate(pieces)


def bar_polyline(trajectory: MarionetteTrajectory, f: int) -> np.ndarray:
    ends = np.array([[-_BAR_HALF_LENGTH, 0, 0], [_BAR_HALF_LENGTH, 0, 0]])
    pieces = []
    for b in range(len(trajectory.bar_names)):
        pieces += [trajectory.bar_pos[f, b] + ends @ trajectory.bar_rot[f, b].T, _NAN]
    return np.concatenate(pieces) if pieces else np.zeros((0, 3))


def draw_chair(ax, chair, axis: int) -> None:
    """Draws the chair box ``(centre, half_extents)`` on ``ax`` as a rectangle in the plane of world
    ``axis`` (0: x, the front view; 2: z, the side view) and y; nothing for None."""
    if chair is None:
        return
    from matplotlib.patches import Rectangle

    c, h = chair
    ax.add_patch(Rectangle((c[axis] - h[axis], c[1] - h[1]), 2 * h[axis], 2 * h[1], color="tan", alpha=0.7))


def frame_extent(trajectory: MarionetteTrajectory, *, chair=None, ball_radius: float | None = None,
                 margin: float = 0.08, ball_reach: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The box the views show [m]: the puppet's bodies (with their size) and the bars over the whole
    run, the chair, and the ball where it is within ``ball_reach`` of them (a ball kicked away leaves
    the picture; the view then says where it is), grown by ``margin``. Returns ``(lo, hi)``, each ``(3,)``."""
    has_ball = ball_radius is not None
    bodies = trajectory.body_pos[:, :-1] if has_ball else trajectory.body_pos
    reach = np.array([0.5 * float(np.linalg.norm(size)) if shape == "box" else float(size[0])
                      for shape, size in trajectory.body_shape[:bodies.shape[1]]])
    lo = (bodies - reach[None, :, None]).reshape(-1, 3).min(axis=0)
    hi = (bodies + reach[None, :, None]).reshape(-1, 3).max(axis=0)
    if trajectory.bar_pos.size:
        along = _BAR_HALF_LENGTH * trajectory.bar_rot[..., :, 0]  # the bar's own x axis in the world
        ends = np.concatenate([(trajectory.bar_pos - along).reshape(-1, 3), (trajectory.bar_pos + along).reshape(-1, 3)])
        lo, hi = np.minimum(lo, ends.min(axis=0)), np.maximum(hi, ends.max(axis=0))
    if chair is not None:
        c, h = np.asarray(chair[0], dtype=float), np.asarray(chair[1], dtype=float)
        lo, hi = np.minimum(lo, c - h), np.maximum(hi, c + h)
    if has_ball:
        ball = np.clip(trajectory.body_pos[:, -1], lo - ball_reach, hi + ball_reach)
        lo, hi = np.minimum(lo, ball.min(axis=0) - ball_radius), np.maximum(hi, ball.max(axis=0) + ball_radius)
    return lo - margin, hi + margin


def _thin(values: np.ndarray, limit: int = 2000) -> slice:
    return slice(None, None, max(1, len(values) // limit))


def render_marionette_animation(path: str | Path, trajectory: MarionetteTrajectory, *, title: str = "",
                                ground_height: float = 0.0, chair=None, ball_radius: float | None = None,
                                fps: float | None = None, every: int = 1, progress: bool = False,
                                dpi: int = 80) -> tuple[Path, int]:
    """Writes the animation (``.gif`` or ``.mp4`` by suffix); returns ``(path, frame count)``.

    Args:
        path: the file to write.
        trajectory: the marionette trajectory.
        title: the heading (the frame's time is added).
        ground_height: the ground plane's height [m].
        chair: ``(centre, half_extents)`` of the chair box [m], or None.
        ball_radius: the ball's radius [m] when the scene has one (the last body), or None.
        fps: frames per second of the animation (default: real time, one frame per ``every``
            trajectory frames).
        every: draw every ``every``-th trajectory frame.
        progress: show a tqdm bar over the frames on stderr.
        dpi: pixels per inch of the 12 x 5 inch figure.
    """
    plt = headless_pyplot("animations")
    try:
        from PIL import Image
    except ImportError:
        raise RuntimeError("animations need Pillow: pip install -e '.[viz]'") from None

    path = Path(path)
    if path.suffix not in (".gif", ".mp4"):
        raise ValueError(f"animation file {str(path)!r}: expected a .gif or .mp4 suffix")
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = range(0, len(trajectory.frame_time), every)
    fps = fps or 1.0 / (trajectory.frame_time[1] - trajectory.frame_time[0]) / every
    lo, hi = frame_extent(trajectory, chair=chair, ball_radius=ball_radius)
    if ground_height >= lo[1] - 0.3:  # the ground is in the picture when the puppet is near it
        lo[1] = min(lo[1], ground_height - 0.05)
    step_time = trajectory.step_time
    reaction = np.linalg.norm(trajectory.bar_reaction, axis=2)
    tension = np.linalg.norm(trajectory.tie_force, axis=2)

    fig = plt.figure(figsize=(12, 5), dpi=dpi)
    grid = fig.add_gridspec(2, 3, width_ratios=[1, 1, 1.25])
    views = [fig.add_subplot(grid[:, 0]), fig.add_subplot(grid[:, 1])]
    force_axes = [fig.add_subplot(grid[0, 2]), fig.add_subplot(grid[1, 2])]
    moving = []  # the artists drawn anew on every frame

    def animated(artist):
        artist.set_animated(True)
        moving.append(artist)
        return artist

    view_artists = []
    for ax, (axis, name) in zip(views, ((0, "x [m] (front)"), (2, "z [m] (side)"))):
        ax.set_xlim(lo[axis], hi[axis])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal", adjustable="box")
        ax.axhspan(min(lo[1], ground_height) - 1.0, ground_height, color="0.85", zorder=0)
        ax.set_xlabel(name)
        ax.tick_params(labelsize=7)
        draw_chair(ax, chair, axis)
        strings = [animated(ax.plot([], [], lw=0.9)[0]) for _ in trajectory.string_names]
        bodies = animated(ax.plot([], [], color="steelblue", lw=1.0)[0])
        bars = animated(ax.plot([], [], color="saddlebrown", lw=4, solid_capstyle="butt")[0])
        ball = away = None
        if ball_radius is not None:
            ball = animated(ax.add_patch(plt.Circle((0, 0), ball_radius, color="crimson", alpha=0.6)))
            away = animated(ax.text(0.02, 0.98, "", transform=ax.transAxes, fontsize=7, color="crimson",
                                    va="top"))
        view_artists.append((axis, strings, bodies, bars, ball, away))
    views[0].set_ylabel("y [m]")

    colours = plt.get_cmap("tab10")
    panels = []
    for ax, values, names, label in (
            (force_axes[0], reaction, [f"{n} bar" for n in trajectory.bar_names], "bar reaction [N]"),
            (force_axes[1], tension, list(trajectory.string_names), "string tension [N]")):
        thin = _thin(step_time)
        for k, name in enumerate(names):
            ax.plot(step_time[thin], values[thin, k], lw=0.9, color=colours(k % 10), label=name)
        top = float(values.max()) if values.size else 0.0
        ax.set_xlim(0, max(float(step_time[-1]), 1e-6))
        ax.set_ylim(0, max(1e-6, 1.08 * top))
        ax.set_ylabel(label, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        if names:
            ax.legend(loc="upper right", fontsize=6, ncol=3 if len(names) > 3 else 1, framealpha=0.7)
        cursor = animated(ax.axvline(0.0, color="0.3", lw=0.8))
        dots = animated(ax.scatter(np.zeros(len(names)), np.zeros(len(names)), s=10, zorder=3,
                                   c=[colours(k % 10) for k in range(len(names))]))
        panels.append((values, cursor, dots))
    force_axes[0].set_title("what the device feels (per bar) and what the puppet feels (per string)", fontsize=8)
    force_axes[1].set_xlabel("time [s]", fontsize=8)
    heading = fig.suptitle(title)
    fig.tight_layout()
    heading = animated(heading)
    fig.canvas.draw()  # everything that does not move: drawn once
    background = fig.canvas.copy_from_bbox(fig.bbox)

    def draw(f: int) -> np.ndarray:
        fig.canvas.restore_region(background)
        step = min(len(trajectory.string_taut) - 1, max(0, f * trajectory.frame_steps - 1))
        body_line, bar_line = body_polyline(trajectory, f), bar_polyline(trajectory, f)
        for axis, strings, bodies, bars, ball, away in view_artists:
            for s, line in enumerate(strings):
                a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
                line.set_data(trajectory.particle_q[f, a:b, axis], trajectory.particle_q[f, a:b, 1])
                line.set_color("0.15" if (trajectory.string_taut[step, s] or f == 0) else "darkorange")
            bodies.set_data(body_line[:, axis], body_line[:, 1])
            bars.set_data(bar_line[:, axis], bar_line[:, 1])
            if ball is not None:
                centre = trajectory.body_pos[f, -1]
                ball.center = (centre[axis], centre[1])
                outside = not lo[axis] <= centre[axis] <= hi[axis]
                away.set_text(f"ball out of view at {'xyz'[axis]} = {centre[axis]:.2f} m" if outside else "")
        t = float(trajectory.frame_time[f])
        for values, cursor, dots in panels:
            cursor.set_xdata([t, t])
            k = min(len(step_time) - 1, int(np.searchsorted(step_time, t)))
            dots.set_offsets(np.stack([np.full(values.shape[1], step_time[k]), values[k]], axis=1))
        heading.set_text(f"{title}   t = {t:.2f} s")
        for artist in moving:
            (fig if artist is heading else artist.axes).draw_artist(artist)
        return np.asarray(fig.canvas.buffer_rgba())  # (height, width, 4), the canvas's own buffer

    count = 0
    bar = tqdm(total=len(frames), unit="frame", desc=f"rendering {path.name}", disable=not progress)
    try:
        if path.suffix == ".gif":
            images = []
            for f in frames:
                rgba = draw(f)  # no copy: Pillow reads the canvas's buffer, the palette image is new
                image = Image.frombuffer("RGBA", (rgba.shape[1], rgba.shape[0]), rgba, "raw", "RGBA", 0, 1)
                images.append(image.quantize(colors=255, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE))
                bar.update()
            delays = gif_delays_ms(len(images), fps)
            images[0].save(path, save_all=True, append_images=images[1:], duration=delays, loop=0,
                           optimize=False, disposal=1)
            count = len(images)
        else:
            try:
                import imageio.v2 as imageio
                import imageio_ffmpeg  # noqa: F401  (the ffmpeg binary)
            except ImportError:
                raise RuntimeError("MP4 animations need imageio-ffmpeg: pip install -e '.[mp4]'") from None
            with imageio.get_writer(path, fps=fps, macro_block_size=8) as writer:
                for f in frames:
                    writer.append_data(draw(f)[:, :, :3].copy())
                    count += 1
                    bar.update()
    finally:
        bar.close()
        plt.close(fig)
    return path, count
