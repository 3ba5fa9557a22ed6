"""Episodes as videos in the book.

Frames in, an H.264 MP4 out (``imageio`` with the ffmpeg binary that ``imageio-ffmpeg``
ships inside its wheel), shown by ``show_video`` as an HTML5 ``<video>`` (looping, muted,
with controls and a poster frame: the episode's last) inside the page, captioned,
labelled and numbered with the figures (the same output metadata as ``show``'s).  The
video travels inside the page as a ``data:`` URI, so the built book plays it with no
network, no CDN and no script; in Jupyter the same output plays in the notebook.  Without
the encoder the episode becomes an animated WebP through Pillow, said once.

The helpers before ``encode`` build frames: ``rgb_frames`` colours a stack of scalar
images, ``enlarge`` scales them up by whole pixels, ``titled`` writes a title band over
a clip and ``side_by_side`` puts clips in one row (``one_above_another`` in one column), so
that a comparison plays in step.
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass

import numpy as np

# a video under 1 MB at the column's width (the budget; a page's under 10 MB)
MAX_BYTES = 1_000_000
FPS = 20
# a white band under every book video: the player's control bar covers the bottom of the
# picture, and would hide what an episode shows there (Point-Maze's start zone)
CONTROLS_PX = 36
# the encoder's quality steps, best first: the first that fits MAX_BYTES is kept
CRF_STEPS = (23, 28, 33, 38)
_said_fallback = False


@dataclass(frozen=True)
class Video:
    """An encoded episode: its bytes, their MIME type, frame count and size in pixels."""

    data: bytes
    mime: str
    frames: int
    width: int
    height: int


def rgb_frames(frames, cmap: str = "magma", vmax: float | None = None) -> np.ndarray:
    """``frames`` as ``(T, H, W, 3)`` uint8: RGB uint8 frames pass as they are, RGB
    floats in [0, 1] are scaled, and scalar frames ``(T, H, W)`` are coloured by ``cmap``
    from 0 to ``vmax`` (their largest value when ``None``), as ``show_frame`` draws one."""
    x = np.asarray(frames)
    if x.ndim == 4 and x.shape[-1] == 3:
        if x.dtype == np.uint8:
            return x
        return (np.clip(x, 0.0, 1.0) * 255).round().astype(np.uint8)
    if x.ndim != 3:
        raise ValueError(f"frames must be (T, H, W) or (T, H, W, 3), got shape {x.shape}")
    from matplotlib import colormaps

    top = float(np.nanmax(x)) if vmax is None else float(vmax)
    scaled = np.clip(np.nan_to_num(x) / (top if top > 0 else 1.0), 0.0, 1.0)
    return (colormaps[cmap](scaled)[..., :3] * 255).round().astype(np.uint8)


def flat_clips(clips: dict[str, np.ndarray], top: float, first_shared: bool = True) -> list[str]:
    """The names of ``clips`` (one channel's frames ``(T, H, W)`` each) that play in one
    colour on the scale ``[0, top]`` (``rgb_frames(..., vmax=top)``): clipped to it, as
    drawn, their values span at most ``FLAT`` of it, the rule ``degeneracies`` applies to
    an image.  With ``first_shared`` the first frame, which predictions unrolled from the
    truth's first frame share with it, is left out."""
    from qdnb.plotting import FLAT

    start = 1 if first_shared else 0
    return [name for name, c in clips.items() if np.ptp(np.clip(c[start:], 0, top)) <= FLAT * top]


def enlarge(frames: np.ndarray, factor: int) -> np.ndarray:
    """Every pixel of ``(T, H, W, C)`` frames as a ``factor`` x ``factor`` block."""
    if factor < 1:
        raise ValueError(f"factor must be a positive integer, got {factor}")
    return np.repeat(np.repeat(frames, factor, axis=1), factor, axis=2)


def titled(frames: np.ndarray, text: str, band: int = 20) -> np.ndarray:
    """RGB ``frames`` under a white band ``band`` pixels high with ``text`` centred in
    it (Pillow's default font at 65 % of the band), the same on every frame."""
    from PIL import Image, ImageDraw, ImageFont

    frames = rgb_frames(frames)
    width = frames.shape[2]
    image = Image.new("RGB", (width, band), "white")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default(size=round(band * 0.65))
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    xy = ((width - (right - left)) / 2, (band - (bottom - top)) / 2 - top)
    draw.text(xy, text, fill="black", font=font)
    head = np.broadcast_to(np.asarray(image), (frames.shape[0], band, width, 3))
    return np.concatenate([head, frames], axis=1)


def side_by_side(clips: list[np.ndarray], gap: int = 6) -> np.ndarray:
    """RGB clips in one row, ``gap`` white pixels apart, playing in step: a shorter clip
    holds its last frame, a shorter one is padded white at the bottom."""
    if not clips:
        raise ValueError("side_by_side needs at least one clip")
    clips = [rgb_frames(c) for c in clips]
    length = max(c.shape[0] for c in clips)
    height = max(c.shape[1] for c in clips)
    parts = []
    for i, c in enumerate(clips):
        c = np.concatenate([c, np.repeat(c[-1:], length - c.shape[0], axis=0)])
        c = np.pad(c, ((0, 0), (0, height - c.shape[1]), (0, 0), (0, 0)), constant_values=255)
        if i:
            parts.append(np.full((length, height, gap, 3), 255, np.uint8))
        parts.append(c)
    return np.concatenate(parts, axis=2)


def one_above_another(clips: list[np.ndarray], gap: int = 6) -> np.ndarray:
    """RGB clips in one column, ``gap`` white pixels apart, playing in step (as
    ``side_by_side``, turned)."""
    turned = [np.swapaxes(rgb_frames(c), 1, 2) for c in clips]
    return np.swapaxes(side_by_side(turned, gap), 1, 2)


def _even(frames: np.ndarray) -> np.ndarray:
    """Frames padded white to even sides (H.264's 4:2:0 colour needs them)."""
    _, h, w, _ = frames.shape
    return np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), constant_values=255)


def encoder() -> str | None:
    """Why no H.264 encoder is at hand, or ``None`` when there is one."""
    try:
        import imageio.v3  # noqa: F401
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as e:
        return f"imageio-ffmpeg is not usable ({e})"
    return None


def encode(frames, fps: int = FPS, max_bytes: int = MAX_BYTES) -> Video:
    """``frames`` (``rgb_frames``' forms) as an H.264 MP4 at ``fps`` frames a second,
    at the best quality of ``CRF_STEPS`` under ``max_bytes``; an animated WebP when no
    encoder is at hand (``encoder``), said once.  ``ValueError`` when even the lowest
    quality does not fit: fewer frames or smaller ones, then."""
    global _said_fallback
    frames = _even(rgb_frames(frames))
    t, h, w, _ = frames.shape
    why = encoder()
    if why is not None:
        if not _said_fallback:
            print(f"Videos are animated WebP images: {why}.")
            _said_fallback = True
        data, mime = _webp(frames, fps), "image/webp"
    else:
        import imageio.v3 as iio

        for crf in CRF_STEPS:
            data = _quiet_imwrite(
                iio,
                "<bytes>",
                frames,
                extension=".mp4",
                fps=fps,
                codec="libx264",
                pixelformat="yuv420p",
                macro_block_size=1,
                output_params=["-crf", str(crf), "-movflags", "+faststart"],
            )
            if len(data) <= max_bytes:
                break
        mime = "video/mp4"
    if len(data) > max_bytes:
        raise ValueError(
            f"a {t}-frame {w}x{h} video takes {len(data) / 1e6:.2f} MB, over the "
            f"{max_bytes / 1e6:.2f} MB a video may: use fewer frames or smaller ones"
        )
    return Video(data, mime, t, w, h)


def _quiet_imwrite(iio, *args, **kwargs) -> bytes:
    """``iio.imwrite`` without JAX's warning that ffmpeg's process was forked from a
    multithreaded one: the child runs ffmpeg at once (``subprocess`` forks and execs in one
    call), never JAX, so the deadlock it warns of cannot happen; on a page it would read
    as an error."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning
        )
        return iio.imwrite(*args, **kwargs)


def _webp(frames: np.ndarray, fps: int) -> bytes:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    buffer = io.BytesIO()
    images[0].save(
        buffer,
        format="WEBP",
        save_all=True,
        append_images=images[1:],
        duration=round(1000 / fps),
        loop=0,
        quality=80,
    )
    return buffer.getvalue()


def decode(video: Video) -> np.ndarray:
    """The frames of ``video`` back, ``(T, H, W, 3)`` uint8 (for tests and checks)."""
    if video.mime == "image/webp":
        from PIL import Image, ImageSequence

        image = Image.open(io.BytesIO(video.data))
        return np.stack([np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(image)])
    import imageio.v3 as iio

    return np.asarray(iio.imread(video.data, extension=".mp4", index=None))


def _png(frame: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(frame).save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def video_html(video: Video, poster: bytes, alt: str) -> str:
    """The HTML a page shows ``video`` with: a ``<video>`` with controls, looping and
    muted, ``poster`` (PNG bytes) before it plays, never wider than the column; an
    animated WebP as an image."""
    src = f"data:{video.mime};base64,{base64.b64encode(video.data).decode()}"
    label = html.escape(alt, quote=True)
    style = f'style="max-width: 100%; height: auto;" width="{video.width}"'
    if video.mime.startswith("image/"):
        return f'<img class="qdnb-video" src="{src}" alt="{label}" {style}>'
    cover = f"data:image/png;base64,{base64.b64encode(poster).decode()}"
    return (
        f'<video class="qdnb-video" controls loop muted playsinline preload="auto" {style} '
        f'height="{video.height}" poster="{cover}" '
        f'aria-label="{label}" title="{label}">'
        f'<source src="{src}" type="{video.mime}">{label}</video>'
    )


def show_video(frames, caption: str, alt: str, name: str | None = None, fps: int = FPS) -> Video:
    """Display ``frames`` as a video of the book (``encode``), captioned, labelled and
    numbered with the figures: ``caption`` (MyST Markdown, beneath it), ``alt`` (what
    it shows, for a reader who cannot see it) and ``name``, a label other text can refer
    to.  A video wider than the column (``COLUMN_INCHES`` at ``DISPLAY_DPI``) is
    refused, as a figure is; a white band (``CONTROLS_PX``) under the picture keeps the
    player's controls off it.  Returns nothing, as ``show`` (a cell ending with it shows
    no repr)."""
    from IPython.display import display

    from qdnb.plotting import COLUMN_INCHES, DISPLAY_DPI, FIGURE_KEY

    if not caption.strip() or not alt.strip():
        raise ValueError("a book video needs a caption and an alt text")
    frames = rgb_frames(frames)
    column = round(COLUMN_INCHES * DISPLAY_DPI)
    if frames.shape[2] > column:
        raise ValueError(
            f"a video {frames.shape[2]} px wide does not fit the page's column ({column} px): "
            "smaller frames, or fewer side by side"
        )
    frames = np.pad(frames, ((0, 0), (0, CONTROLS_PX), (0, 0), (0, 0)), constant_values=255)
    video = encode(frames, fps)
    poster = _png(_even(frames[-1:])[0])
    display(
        {
            "text/html": video_html(video, poster, alt),
            "image/png": base64.b64encode(poster).decode(),
            "text/plain": f"<Video: {alt}>",
        },
        raw=True,
        metadata={
            "image/png": {"width": video.width, "height": video.height},
            FIGURE_KEY: {"caption": caption, "alt": alt, "name": name or "", "video": True},
        },
    )


def maze_frames(path, size: int = 200, color: str = "#9467bd", every: int = 2) -> np.ndarray:
    """A Point-Maze episode as RGB frames ``(T', size, size, 3)``: the walls, the goal
    zone (green) and the start zone (orange), the path walked so far in ``color`` and the
    point as a dot, one frame per ``every`` steps of ``path`` ``(T, 2)`` (positions in
    the arena ``[-1, 1]^2``; an episode that ended early holds its last position)."""
    from PIL import Image, ImageColor, ImageDraw

    from qdnb.envs.pointmaze import GOAL, GOAL_HALF_SIDE, WALLS

    path = np.asarray(path, float)
    if path.ndim != 2 or path.shape[1] != 2 or len(path) == 0:
        raise ValueError(f"path must be (T, 2) positions, got shape {path.shape}")

    def px(x, y):  # arena to pixels, y up
        return (x + 1) / 2 * (size - 1), (1 - (y + 1) / 2) * (size - 1)

    base = Image.new("RGB", (size, size), "white")
    draw = ImageDraw.Draw(base)
    draw.rectangle([0, 0, size - 1, size - 1], outline=(190, 190, 190))
    for x0, x1, y0, y1 in WALLS:
        (a, b), (c, d) = px(x0, y1 + 0.01), px(x1, y0 - 0.01)
        draw.rectangle([a, b, c, d], fill=(77, 77, 77))
    g = GOAL_HALF_SIDE
    draw.rectangle(
        [*px(GOAL[0] - g, GOAL[1] + g), *px(GOAL[0] + g, GOAL[1] - g)],
        outline=(50, 205, 50),
        width=2,
    )
    draw.rectangle([*px(-0.1, -0.7), *px(0.1, -1.0)], outline=(255, 165, 0))
    rgb = ImageColor.getrgb(color)
    points = [px(x, y) for x, y in path]
    radius = max(2, size // 60)
    frames = []
    for t in list(range(0, len(points), every)) + (
        [len(points) - 1] if (len(points) - 1) % every else []
    ):
        image = base.copy()
        draw = ImageDraw.Draw(image)
        if t:
            draw.line(points[: t + 1], fill=rgb, width=2)
        x, y = points[t]
        draw.ellipse([x - radius, y - radius, x + radius, y + radius], fill=rgb, outline="black")
        frames.append(np.asarray(image))
    return np.stack(frames)
