"""Shared figure style and the plots every chapter uses: repertoire maps (grid
and CVT alike), quartile curves, and the Point-Maze layout."""

from __future__ import annotations

from typing import Sequence

import matplotlib.pyplot as plt
import numpy as np

from qdnb.core.names import (
    ENV_LABELS,  # noqa: F401  (the notebooks' labels)
    number_text,
)
from qdnb.plotting.tables import loop_costs, use_book_tables  # noqa: F401 (for the pages)

# One colour per method across the book (a QDT takes the colour of the repertoire it learns from).
METHOD_COLORS = {
    "GA": "#7f7f7f",
    "NS": "#17becf",  # Chapters 1-2
    "ME": "#d62728",
    "ME-LS": "#1f77b4",
    "PGA-ME": "#ff7f0e",
    "PGA-ME-LS": "#2ca02c",
    "ME-Sampling": "#8c564b",
    "Naive": "#7b4173",  # Chapter 4
    "QD-PG": "#9467bd",
    "QD-PG Sum": "#e377c2",
    "D-PG": "#bcbd22",
    "Q-PG": "#393b79",
    "TD3": "#525252",  # Chapter 3
    "SAC": "#a6761d",
    "RND": "#66a61e",
    "CEM-RL": "#e7298a",
    "P3S-TD3": "#1a9850",
    "AGAC": "#d95f02",
    "DIAYN": "#00bcd4",  # Chapter 3's baselines
    "ME-ES": "#b2182b",
    "NSR-ES": "#2166ac",
    "NSRA-ES": "#4dac26",  # Chapter 3's evolution strategies
    "flt": "#8c6d31",
    "persistence": "#e6ab02",
    "mean_frame": "#1b9e77",  # Chapter 5's predictors
}
# What each axis of an environment's behaviour descriptor measures (QDax's order for the feet)
DESCRIPTOR_LABELS = {
    "ant_omni": ("final x (m)", "final y (m)"),
    "halfcheetah_uni": ("front foot contact (share)", "back foot contact (share)"),
}


# The page's content column, in inches at the figures' display resolution (100 px per
# inch: 680 px, the column of the rendered book at 1280 px wide); a figure never exceeds it,
# so that its 9-point fonts show at 9 points.
COLUMN_INCHES = 6.8
DISPLAY_DPI = 100
FIGURE_KEY = "qdnb_figure"  # the output metadata that makes a displayed image a book figure


def method_color(name: str) -> str:
    """The book's colour of a method (``KeyError`` names the known ones)."""
    if name not in METHOD_COLORS:
        raise KeyError(f"no colour for method {name!r}; known: {', '.join(METHOD_COLORS)}")
    return METHOD_COLORS[name]


def set_style() -> None:
    """One style for every figure and table of the book: 9-point fonts, figures drawn at
    twice their displayed resolution (``show``'s, and in Jupyter any other figure's:
    ``retina``, 200 dpi), and DataFrames shown as ``tables.styled`` tables."""
    use_book_tables()
    try:
        from matplotlib_inline.backend_inline import set_matplotlib_formats

        set_matplotlib_formats("retina")
    except ImportError:  # pragma: no cover - ships with the notebooks' kernel
        pass
    plt.rcParams.update(
        {
            "figure.dpi": DISPLAY_DPI,
            "savefig.dpi": 2 * DISPLAY_DPI,
            "font.size": 9,
            "axes.titlesize": 10,
            "axes.labelsize": 9,
            "xtick.labelsize": 9,
            "ytick.labelsize": 9,
            "legend.fontsize": 9,
            "figure.titlesize": 10,
            "axes.formatter.limits": (-3, 4),  # 250000 reads as 2.5 and x10^5 at the axis end
            "axes.spines.top": False,
            "axes.spines.right": False,
            "axes.grid": True,
            "grid.alpha": 0.25,
            "legend.frameon": False,
        }
    )


DEGENERATE = "Degenerate at this scale:"
# an image whose values span less than this share of its colour scale reads as one colour
FLAT = 0.01
UNEXPLAINED = "no reason given"


def _panel_name(ax: plt.Axes, i: int) -> str:
    title = ax.get_title() or ax.get_ylabel()
    return f"panel {i + 1}" + (f" ({title})" if title else "")


# an axis counting these (its label names one) has integer ticks: no "iteration 0.5"
COUNTS = ("step", "iteration", "epoch", "generation", "evaluation", "trajectories")


def integer_axes(fig: plt.Figure) -> None:
    """Integer ticks on every linear axis of ``fig`` that counts steps, iterations,
    epochs, generations or evaluations (its label says which), colour bars included."""
    from matplotlib.ticker import MaxNLocator

    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            label = axis.get_label().get_text().lower()
            if axis.get_scale() == "linear" and any(word in label for word in COUNTS):
                axis.set_major_locator(MaxNLocator(integer=True))


def _book_ticks(digits: int):
    """A tick formatter in the book's number style (``number_text``), minus signs typeset."""
    from matplotlib.ticker import FuncFormatter

    return FuncFormatter(lambda v, _: number_text(v, digits).replace("-", "\u2212"))


def _drawn_as_line(line) -> bool:
    """Whether ``line`` is drawn as a line (not markers alone)."""
    return line.get_linestyle() not in ("None", "", " ")


def plain_tick_labels(fig: plt.Figure) -> None:
    """Tick labels in the book's number style (``number_text``: 20,000, 2·10⁵) on every
    linear axis whose labels Matplotlib would print against a multiplier ("1e5" at the
    axis's end, which readers misread); an axis whose ticks would not stay distinct at up
    to six significant figures, or that Matplotlib labels against an added offset
    ("+1e3"), keeps Matplotlib's labels."""
    from matplotlib.ticker import ScalarFormatter

    for ax in fig.axes:
        ax.get_xlim(), ax.get_ylim()  # (the limits the ticks are placed in, autoscaled)
        for axis in (ax.xaxis, ax.yaxis):
            formatter = axis.get_major_formatter()
            if axis.get_scale() != "linear" or type(formatter) is not ScalarFormatter:
                continue
            locs = [v for v in axis.get_majorticklocs() if np.isfinite(v)]
            formatter.set_locs(locs)
            if not formatter.get_offset() or formatter.offset:  # (an added offset: left)
                continue
            for digits in range(3, 7):
                labels = [number_text(v, digits) for v in locs]
                if len(set(labels)) == len(labels):
                    axis.set_major_formatter(_book_ticks(digits))
                    break


def log_ticks(fig: plt.Figure) -> None:
    """Readable ticks on every log axis of ``fig`` that spans less than a decade or two,
    where Matplotlib labels one power of ten or none: ticks at 1, 2 and 5 times the powers
    of ten, labelled in the book's style (``number_text``), the minor ones unlabelled."""
    from matplotlib.ticker import LogLocator, NullFormatter

    for ax in fig.axes:
        ax.get_xlim(), ax.get_ylim()
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() != "log":
                continue
            low, high = sorted(axis.get_view_interval())
            majors = [v for v in axis.get_majorticklocs() if low <= v <= high]
            if len(majors) >= 2:
                continue
            axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(_book_ticks(2))
            axis.set_minor_formatter(NullFormatter())


def _labels_collide(axis, renderer) -> bool:
    """Whether two of ``axis``'s visible tick labels overlap or come within 2 points of
    each other (labels that touch read as one number)."""
    gap = renderer.points_to_pixels(2.0) / 2
    boxes = [
        t.label1.get_window_extent(renderer).padded(gap)
        for t in axis.get_major_ticks()
        if t.label1.get_visible() and t.label1.get_text()
    ]
    return any(a.overlaps(b) for a, b in zip(boxes, boxes[1:]))


def thin_ticks(fig: plt.Figure) -> None:
    """Fewer ticks on every linear axis of ``fig`` whose tick labels run into each other
    (a narrow panel of long numbers): as many as fit, integer ones where they were."""
    from matplotlib.ticker import FixedLocator, MaxNLocator

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() != "linear" or isinstance(axis.get_major_locator(), FixedLocator):
                continue  # (ticks placed by hand, often with their own labels, stay)
            if not _labels_collide(axis, renderer):
                continue
            integer = getattr(axis.get_major_locator(), "_integer", False)
            for bins in (6, 5, 4, 3, 2):
                axis.set_major_locator(MaxNLocator(nbins=bins, integer=integer))
                fig.canvas.draw()
                if not _labels_collide(axis, renderer):
                    break


def _within(points: np.ndarray, box) -> np.ndarray:
    """Which of the ``(n, 2)`` display ``points`` lie in ``box`` (a Bbox), edges included."""
    x, y = points[:, 0], points[:, 1]
    return (x >= box.x0) & (x <= box.x1) & (y >= box.y0) & (y <= box.y1)


def _display_points(line) -> np.ndarray:
    """A curve's finite vertices in display coordinates (pixels on the page)."""
    xy = line.get_transform().transform(line.get_xydata())
    return xy[np.all(np.isfinite(xy), axis=1)]


def _data_points(ax: plt.Axes) -> np.ndarray:
    """The display coordinates of what ``ax`` draws as data: its curves' vertices, its
    scatters' points and its arrows' tails inside the panel (bands and images are
    backgrounds a legend may sit on)."""
    from matplotlib.collections import PathCollection
    from matplotlib.quiver import Quiver

    points = [_display_points(line) for line in ax.lines]
    points += [
        c.get_offset_transform().transform(np.asarray(c.get_offsets(), dtype=float))
        for c in ax.collections
        if isinstance(c, (PathCollection, Quiver))  # a scatter's points, arrows' tails
    ]
    points = [p for p in points if np.size(p)]
    if not points:
        return np.zeros((0, 2))
    p = np.concatenate(points)
    # what the panel clips away is not drawn
    return p[np.all(np.isfinite(p), axis=1) & _within(p, ax.bbox)]


def legend_overlaps(ax: plt.Axes, renderer) -> int:
    """How many of ``ax``'s data points (``_data_points``) its legend covers."""
    legend = ax.get_legend()
    if legend is None:
        return 0
    return int(_within(_data_points(ax), legend.get_window_extent(renderer)).sum())


def clear_legends(fig: plt.Figure) -> None:
    """Keep every panel's legend off its data: a legend that covers curve vertices or
    scatter points moves to where it covers the fewest (Matplotlib's "best" place), or,
    when every place inside the panel covers some, below the panel, under its axis
    label, unless another panel is there.  Figure-level legends are placed by their
    makers, outside the panels."""
    fig.canvas.draw()  # the legends' places, as drawn
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is None or not legend_overlaps(ax, renderer):
            continue
        legend.set_loc("best")
        fig.canvas.draw()
        if not legend_overlaps(ax, renderer):
            continue
        below = ax.get_tightbbox(renderer).transformed(ax.transAxes.inverted()).y0
        legend.set_loc("upper center")
        legend.set_bbox_to_anchor((0.5, below - 0.02), transform=ax.transAxes)
        fig.canvas.draw()
        box = legend.get_window_extent(renderer)
        others = [a.get_tightbbox(renderer) for a in fig.axes if a is not ax and a.get_visible()]
        if any(other is not None and box.overlaps(other) for other in others):
            legend.set_loc("best")  # below would cover the next panel: the least covering place
            legend.set_bbox_to_anchor(None)


def _unseen(line, ax: plt.Axes) -> str | None:
    """Why ``line`` draws nothing a reader can see in ``ax``, or ``None`` when it does:
    values a log axis cannot place (zero or below), or none inside the panel."""
    y = _finite(line.get_ydata())
    if y is None or y.size == 0:
        return None
    if ax.get_yscale() == "log" and np.all(y <= 0):
        return f"at {number_text(float(y.max()))}, off the log scale"
    return None if _within(_display_points(line), ax.bbox).any() else "outside the panel"


def _covers(top, under) -> bool:
    """Whether the curve ``top``, drawn over ``under``, hides it: every vertex of
    ``under`` lies within half ``top``'s line width of ``top``'s path, on the page."""
    if not (_drawn_as_line(top) and _drawn_as_line(under)):
        return False
    path, points = _display_points(top), _display_points(under)
    if len(path) == 0 or len(points) == 0:
        return False
    width = top.figure.dpi / 72 * top.get_linewidth() / 2
    if np.any(points.min(0) < path.min(0) - width) or np.any(points.max(0) > path.max(0) + width):
        return False  # (outside the box around top's path: apart, without the distances)
    points = points[:: max(1, len(points) // 500)]
    if len(path) == 1:
        return bool(np.all(np.linalg.norm(points - path[0], axis=1) <= width))
    a, b = path[:-1], path[1:]
    ab = b - a
    length = np.maximum((ab**2).sum(axis=1), 1e-12)
    # each point's distance to each segment, then to the nearest one
    t = np.clip(((points[:, None] - a[None]) * ab[None]).sum(-1) / length[None], 0.0, 1.0)
    nearest = a[None] + t[..., None] * ab[None]
    distance = np.linalg.norm(points[:, None] - nearest, axis=-1).min(axis=1)
    return bool(np.all(distance <= width))


def name_unseen_lines(fig: plt.Figure) -> None:
    """A legend entry whose curve a reader cannot find says why: the curve lies off the
    panel (``_unseen``: "replay floor (at 0, off the log scale)") or under a curve drawn
    after it, within half that curve's line width (``_covers``: "NSR-ES (under
    NSRA-ES)")."""
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is None:
            continue
        ax.get_xlim(), ax.get_ylim()  # (the view limits the curves are placed in, autoscaled)
        lines = [line for line in ax.lines if not line.get_label().startswith("_")]
        texts = {t.get_text(): t for t in legend.get_texts()}
        for i, line in enumerate(lines):
            text = texts.get(line.get_label())
            if text is None:
                continue
            why = _unseen(line, ax)
            if why is None:
                above = [later.get_label() for later in lines[i + 1 :] if _covers(later, line)]
                why = f"under {above[-1]}" if above else None
            if why:
                text.set_text(f"{text.get_text()} ({why})")


def degeneracies(fig: plt.Figure) -> list[str]:
    """What a reader would see as broken in ``fig``: a uniform image (its values, as
    drawn, clipped to its colour scale, span less than ``FLAT`` of that scale), a panel
    whose data are all NaN, a colour scale with one value, a curve of a single point."""
    found, beyond = [], []
    panels = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    for i, ax in enumerate(panels):
        name = _panel_name(ax, i)
        for im in ax.images:
            values = np.ma.masked_invalid(np.ma.asarray(im.get_array(), dtype=float))
            if values.count() == 0:
                found.append(f"{name} is an image with no finite value")
                continue
            if values.ndim != 2:  # an RGB image carries its own colours
                continue
            im.autoscale_None()  # the colour scale it is drawn with, as drawing sets it
            scale = float(im.norm.vmax - im.norm.vmin)
            span = float(values.max() - values.min())
            if scale > 0 and span > FLAT * scale:  # as drawn: beyond the scale, its end colours
                shown = np.clip(values, im.norm.vmin, im.norm.vmax)
                if float(shown.max() - shown.min()) <= FLAT * scale:
                    beyond.append(
                        (
                            name,
                            f"{number_text(values.min(), 3)} to {number_text(values.max(), 3)}",
                            f"{number_text(im.norm.vmin, 3)} to {number_text(im.norm.vmax, 3)}",
                        )
                    )
                continue
            if span <= FLAT * (scale if scale > 0 else abs(float(values.max()))):
                found.append(
                    f"{name} is a uniform image ({float(values.mean()):.3g}"
                    + (f", varying by {span:.2g}" if span else "")
                    + ")"
                )
        # the panel's curves (lines drawn as lines, not markers alone), when it has
        # nothing else (an image, a scatter, a band) to show
        curves = [line for line in ax.lines if _drawn_as_line(line)]
        values = [_finite(c.get_ydata()) for c in curves]
        finite = [None if v is None else v.size for v in values]
        if curves and not ax.images and not ax.collections and None not in finite:
            if max(finite) == 0:
                found.append(f"{name} has no finite value to draw")
            elif max(finite) == 1:
                found.append(f"{name} draws each curve as a single point")
    if len(beyond) == 1:
        name, values, scale = beyond[0]
        found.append(
            f"{name} is drawn in one colour: its values ({values}) lie beyond its colour "
            f"scale ({scale})"
        )
    elif beyond:  # one entry for them all, the first as the example
        names = [b[0].split(" (")[0] for b in beyond]
        found.append(
            f"panels {', '.join(n.removeprefix('panel ') for n in names[:-1])} and "
            f"{names[-1].removeprefix('panel ')} are drawn in one colour: their values lie "
            f"beyond their colour scales ({beyond[0][1]} against {beyond[0][2]} in the first)"
        )
    for ax in fig.axes:
        bar = getattr(ax, "_colorbar", None)
        values = None if bar is None else _finite(bar.mappable.get_array())
        if values is not None and values.size and values.min() == values.max():
            found.append(f"a colour bar spans a single value ({float(values[0]):.3g})")
    return found


def _finite(data) -> np.ndarray | None:
    """The finite, unmasked values of ``data`` as floats; ``None`` for data that are not
    numbers (dates, categories) or no data."""
    if data is None:
        return None
    try:
        values = np.ma.masked_invalid(np.ma.asarray(data, dtype=float))
    except (TypeError, ValueError):
        return None
    return values.compressed()


def show(
    fig: plt.Figure, caption: str, alt: str, name: str | None = None, note: str | None = None
) -> None:
    """Display ``fig`` as a figure of the book: a PNG at twice its displayed resolution,
    shown at most the page's column wide, with its ``caption`` (MyST Markdown, shown
    beneath it and numbered by the book), its ``alt`` text (what the figure shows, for
    a reader who cannot see it) and ``name``, a label other text can refer to.  In
    Jupyter it shows as any figure.  A figure wider than ``COLUMN_INCHES`` is refused:
    shrunk into the column, its fonts would fall below 9 points.  Axes that count
    (``integer_axes``) get integer ticks, ticks print without a multiplier
    (``plain_tick_labels``), a short log axis gets labelled ticks (``log_ticks``), tick
    labels that collide are thinned (``thin_ticks``), a legend entry whose curve cannot be
    seen says why (``name_unseen_lines``), and legends move off the data
    (``clear_legends``).  A degenerate figure (``degeneracies``) is never shown
    silently: its caption says what is degenerate and ``note`` why (without a note the
    book's build refuses the page)."""
    import base64
    import io

    from IPython.display import display

    width = fig.get_size_inches()[0]
    if width > COLUMN_INCHES + 1e-6:
        plt.close(fig)
        raise ValueError(
            f"a figure {width:.1f} in wide does not fit the page's column ({COLUMN_INCHES} in): "
            "wrap its panels into rows (panel_grid) or split it"
        )
    if not caption.strip() or not alt.strip():
        plt.close(fig)
        raise ValueError("a book figure needs a caption and an alt text")
    integer_axes(fig)
    plain_tick_labels(fig)
    log_ticks(fig)
    thin_ticks(fig)
    name_unseen_lines(fig)
    clear_legends(fig)
    broken = degeneracies(fig)
    if broken:
        caption = f"{caption.rstrip()} **{DEGENERATE}** {'; '.join(broken)}. " + (
            note.strip() if note and note.strip() else f"({UNEXPLAINED})"
        )
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=2 * DISPLAY_DPI, bbox_inches="tight")
    plt.close(fig)
    png = buffer.getvalue()
    pixels = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    display(
        {"image/png": base64.b64encode(png).decode(), "text/plain": f"<Figure: {alt}>"},
        raw=True,
        metadata={
            "image/png": {"width": pixels[0] // 2, "height": pixels[1] // 2},
            FIGURE_KEY: {"caption": caption, "alt": alt, "name": name or ""},
        },
    )


def figure_title(fig: plt.Figure, text: str, scale: str) -> None:
    """Title that names the thesis figure and the scale it was run at."""
    fig.suptitle(f"{text} — scale: {scale}", fontsize=10)


def repertoire_map(
    ax: plt.Axes,
    centroids: np.ndarray,
    values: np.ndarray,
    low: Sequence[float],
    high: Sequence[float],
    resolution: int = 300,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
):
    """Colour each point of a 2-D descriptor space by the value of its nearest
    centroid: the Voronoi cells of a CVT, or the squares of a grid.  Cells whose
    value is not finite (empty) stay white.  Returns the image for a colour bar."""
    centroids, values = np.asarray(centroids), np.asarray(values, dtype=float)
    xs = np.linspace(low[0], high[0], resolution)
    ys = np.linspace(low[1], high[1], resolution)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=-1)
    cells = np.empty(len(pts), dtype=int)
    for start in range(0, len(pts), 20_000):  # bounded memory for large tessellations
        chunk = pts[start : start + 20_000]
        cells[start : start + 20_000] = np.argmin(
            ((chunk[:, None, :] - centroids[None]) ** 2).sum(-1), axis=1
        )
    image = np.where(np.isfinite(values), values, np.nan)[cells].reshape(resolution, resolution)
    finite = values[np.isfinite(values)]
    im = ax.imshow(
        image,
        origin="lower",
        extent=(low[0], high[0], low[1], high[1]),
        cmap=cmap,
        aspect="auto",
        vmin=vmin if vmin is not None else (finite.min() if finite.size else None),
        vmax=vmax if vmax is not None else (finite.max() if finite.size else None),
        interpolation="nearest",
    )
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.grid(False)
    return im


def quartile_curves(
    ax: plt.Axes, x: np.ndarray, ys: np.ndarray, label: str, color: str | None = None
) -> None:
    """Median over seeds (rows of ``ys``) with the interquartile range shaded."""
    ys = np.asarray(ys)
    q1, med, q3 = np.percentile(ys, [25, 50, 75], axis=0)
    (line,) = ax.plot(x, med, label=label, color=color)
    ax.fill_between(x, q1, q3, color=line.get_color(), alpha=0.25, linewidth=0)


def draw_pointmaze(ax: plt.Axes) -> None:
    """Walls, goal zone and start zone of Point-Maze."""
    from matplotlib.patches import Rectangle

    from qdnb.envs.pointmaze import GOAL, GOAL_HALF_SIDE, WALLS

    # under the points: a policy pressed against a wall ends on its edge, and must show
    for x0, x1, y0, y1 in WALLS:
        ax.add_patch(Rectangle((x0, y0 - 0.01), x1 - x0, (y1 - y0) + 0.02, color="0.3", zorder=0.5))
    g = GOAL_HALF_SIDE
    ax.add_patch(
        Rectangle(
            (GOAL[0] - g, GOAL[1] - g),
            2 * g,
            2 * g,
            facecolor="none",
            edgecolor="limegreen",
            linewidth=2,
            zorder=6,
            label="goal zone",
        )
    )
    ax.add_patch(
        Rectangle(
            (-0.1, -1.0),
            0.2,
            0.3,
            facecolor="none",
            edgecolor="orange",
            linestyle="--",
            linewidth=1.2,
            zorder=6,
            label="start zone",
        )
    )
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_aspect("equal")
    ax.grid(False)


def draw_capsule_walls(ax: plt.Axes, walls, radius: float = 0.5, color: str = "black") -> None:
    """Capsule walls given by their axis end points ``((x0, y0), (x1, y1))``, seen
    from above: a rectangle of width ``2 * radius`` with round ends."""
    from matplotlib.patches import Circle, Polygon

    for (x0, y0), (x1, y1) in walls:
        d = np.array([x1 - x0, y1 - y0], float)
        n = np.array([-d[1], d[0]]) / max(np.linalg.norm(d), 1e-9) * radius
        a, b = np.array([x0, y0], float), np.array([x1, y1], float)
        ax.add_patch(Polygon([a + n, b + n, b - n, a - n], closed=True, color=color, zorder=5))
        for end in (a, b):
            ax.add_patch(Circle(end, radius, color=color, zorder=5))


def panel_grid(
    n: int, ncols: int = 3, aspect: float = 0.9, **kwargs
) -> tuple[plt.Figure, list[plt.Axes]]:
    """``n`` panels wrapped into rows of at most ``ncols``, as the thesis's figures
    are (a row of five panels renders at thumbnail size at the page's width), the
    figure as wide as the page's column (``COLUMN_INCHES``), each panel ``aspect``
    times as high as wide; the unused slots of the last row are hidden.  Returns the
    figure and the ``n`` axes."""
    if n < 1 or ncols < 1:
        raise ValueError(f"n and ncols must be positive, got {n} and {ncols}")
    cols = min(n, ncols)
    rows = -(-n // cols)
    width = COLUMN_INCHES / ncols  # a panel's width, the same for any n
    fig, axes = plt.subplots(
        rows,
        cols,
        figsize=(width * cols, width * aspect * rows + 0.4),
        squeeze=False,
        constrained_layout=True,
        **kwargs,
    )
    flat = list(axes.ravel())
    for ax in flat[n:]:
        ax.set_visible(False)
    return fig, flat[:n]


def show_frame(
    ax: plt.Axes, image: np.ndarray, vmax: float | None = None, cmap: str = "magma"
) -> None:
    """One frame of a grid of frames (a world's state, a density): the image from 0 to
    ``vmax`` (its own maximum when ``None``), without ticks or grid."""
    ax.imshow(np.asarray(image), cmap=cmap, vmin=0, vmax=vmax)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.grid(False)


def reward_arrows(ax: plt.Axes, goal, low, high, n: int = 15) -> None:
    """The direction a distance-to-goal reward pulls towards, on an ``n x n`` lattice
    over ``[low, high]`` (Figure 3.4's deceptive gradients)."""
    xs, ys = np.meshgrid(np.linspace(low[0], high[0], n), np.linspace(low[1], high[1], n))
    d = np.stack([goal[0] - xs, goal[1] - ys])
    d = d / np.maximum(np.linalg.norm(d, axis=0), 1e-9)
    ax.quiver(xs, ys, d[0], d[1], color="tab:blue", alpha=0.8, scale=n * 1.4, width=0.004)


# the colour bar of ``positions_over_time``
TRAINING_SHARE = "share of training done (0: start, 1: end)"


def positions_over_time(ax: plt.Axes, descriptors: np.ndarray, title: str):
    """Every evaluated policy's final position ``(iterations, batch, 2)``, coloured by
    when in training it was evaluated, from 0 (the first iteration) to 1 (the last), so
    panels of runs with different iteration counts share one colour bar (Figure 3.8);
    returns the scatter for that colour bar (``TRAINING_SHARE`` is its label)."""
    iterations = descriptors.shape[0]
    share = np.arange(iterations) / max(iterations - 1, 1)
    share = np.broadcast_to(share[:, None], descriptors.shape[:2])
    sc = ax.scatter(
        descriptors[..., 0].ravel(),
        descriptors[..., 1].ravel(),
        c=share.ravel(),
        cmap="cool",
        vmin=0.0,
        vmax=1.0,
        s=4,
        zorder=3,
    )
    ax.set_title(title, fontsize=10)
    return sc


def coverage_map(
    ax: plt.Axes,
    descriptors: np.ndarray,
    title: str,
    walls: np.ndarray | None = None,
    radius: float = 0.0,
    bounds: tuple | None = None,
):
    """Figure 3.8's panel: ``positions_over_time`` over Point-Maze (``walls`` None) or
    over an ant maze's capsule ``walls`` within ``bounds`` (low, high); returns the
    scatter for a colour bar."""
    sc = positions_over_time(ax, descriptors, title)
    if walls is None:
        draw_pointmaze(ax)
    else:
        draw_capsule_walls(ax, walls, radius)
        (x0, y0), (x1, y1) = bounds
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.grid(False)
    return sc


def outline_pruning(ax: plt.Axes, name: str, low, high, tiles: int, resolution: int = 400) -> None:
    """The region a QDT pruning removes (Figures 4.10 and 4.11), tinted and outlined
    from the same rule that prunes (``removed_region``); nothing for the random prunings."""
    from qdnb.models.qdt.data import removed_region

    xs, ys = np.meshgrid(
        np.linspace(low[0], high[0], resolution), np.linspace(low[1], high[1], resolution)
    )
    points = np.stack([xs.ravel(), ys.ravel()], -1)
    mask = removed_region(name, points, low, high, tiles).reshape(xs.shape)
    if mask.any():
        ax.contourf(xs, ys, mask.astype(float), levels=[0.5, 1.5], colors=["c"], alpha=0.2)
        ax.contour(
            xs, ys, mask.astype(float), levels=[0.5], colors="c", linewidths=1.0, linestyles="--"
        )
