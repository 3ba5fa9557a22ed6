"""What the book's videos cost: drawing the robots and encoding the episodes.

Questions: how long MuJoCo takes to draw a robot frame off screen here (EGL, Mesa's
software rasteriser: the renderer ``qdnb.envs.render`` chose) for each task at the size
the pages use, and how long an H.264 encoding takes and how large it is for each page's
video, against the issue's budgets (a video under 1 MB, a page's videos under 10 MB,
encoding under 10 % of the page's wall time).  ``brax.io.image`` (pytinyrenderer) is not
measured: it is not installed, and would be one more package for a cruder picture.

The frames are synthetic where only their size matters (the encoder's time and bytes
depend on the content, so the maze and Flow Lenia clips are drawn as the pages draw them,
from made-up paths and patterns), and random policies' episodes for the robots.

    python bench/video.py                  # about a minute on 2 cores
    python bench/video.py --pages small    # the pages' own videos, from their executed runs

``--pages SCALE`` reads each page's executed notebook under ``data/runs/SCALE/`` (run it
after ``python -m qdnb run ... --scale SCALE``): per page, every video's size, their total,
and the time of the cells that made them (papermill's per-cell durations: playing the
episodes, drawing and encoding, an upper bound on the encoding alone) against the page's
wall time; written to ``bench/results/video_pages_SCALE.json``.
"""

from __future__ import annotations

import argparse
import base64
import json
import re
import time

import jax
import numpy as np

from qdnb.book.provenance import write_result
from qdnb.core import paths
from qdnb.envs import make_env
from qdnb.envs.render import Camera, episode_states, render, renderer_missing
from qdnb.nets.mlp import MLP
from qdnb.plotting.video import (
    encode,
    enlarge,
    maze_frames,
    one_above_another,
    rgb_frames,
    side_by_side,
    titled,
)

RESULTS = paths.ROOT / "bench" / "results" / "video.json"
# the robots as the pages draw them: (task, width, height, camera, frames)
ROBOTS = (
    ("ant_omni", 200, 150, Camera(distance=6.0, elevation=-55.0, lookat=(0.0, 0.0, 0.0)), 51),
    ("antmaze", 200, 200, Camera(distance=16.0, elevation=-70.0), 100),
    ("halfcheetah_uni", 200, 150, Camera(distance=5.0, elevation=-10.0), 51),
)


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def robot_rows() -> tuple[dict, dict]:
    rows, frames = {}, {}
    for name, width, height, camera, count in ROBOTS:
        env = make_env(name)
        net = MLP((32, env.action_size))
        params = jax.tree.map(
            lambda x: x[None], net.init(jax.random.PRNGKey(0), np.zeros(env.observation_size))
        )
        length = (count - 1) * 5
        (qs, _), play = timed(
            lambda: episode_states(env, net.apply, params, jax.random.PRNGKey(1)[None], length)
        )
        drawn, seconds = timed(lambda: render(env, qs[0, ::5], width, height, camera))
        frames[name] = drawn
        rows[name] = {
            "frames": len(drawn),
            "size": [width, height],
            "episode_seconds": round(play, 2),
            "render_seconds": round(seconds, 2),
            "seconds_per_frame": round(seconds / len(drawn), 4),
        }
    return rows, frames


def page_clips(robots: dict) -> dict[str, np.ndarray]:
    t = np.linspace(0, 1, 201)
    path = np.stack([0.8 * np.sin(4 * t) - 0.1, -0.85 + 1.7 * t], 1)
    maze = [
        titled(maze_frames(path * s, color=c), n)
        for s, c, n in ((1, "#7f7f7f", "GA"), (0.9, "#17becf", "NS"), (0.8, "#d62728", "ME"))
    ]
    h = 32
    yy, xx = np.mgrid[:h, :h] / h
    blob = np.stack([np.exp(-((xx - 0.3 - 0.4 * s) ** 2 + (yy - 0.5) ** 2) / 0.01) for s in t[::4]])
    lenia = [
        titled(enlarge(rgb_frames(blob * k, vmax=1.0), 5), n)
        for k, n in ((1, "truth"), (0.8, "thesis's FLT"), (0.6, "ours"))
    ]
    clips = {"ch2 primer (3 mazes)": side_by_side(maze), "ch5 FLT (3 unrolls)": side_by_side(lenia)}
    if "ant_omni" in robots:
        row = side_by_side([robots["ant_omni"]] * 3)
        clips["ch4 Low-Spread (2 x 3 ants)"] = one_above_another(
            [titled(row, "ME"), titled(row, "ME-LS")], 10
        )
    if "antmaze" in robots:
        clips["ch3 QD-PG/TD3 (mazes and ants)"] = one_above_another(
            [side_by_side(maze[:2]), side_by_side([titled(robots["antmaze"], "QD-PG")] * 2)], 10
        )
    return clips


VIDEO = re.compile(r'src="data:video/\w+;base64,([^"]+)"')


def page_rows(scale: str) -> dict:
    """Each executed page's videos: sizes, and the time of the cells that made them."""
    from qdnb.book import registry

    rows = {}
    for chapter in registry.CHAPTERS:
        run = paths.ROOT / "data" / "runs" / scale / chapter.name
        notebook, execution = run / f"{chapter.name}.ipynb", run / "execution.json"
        if not notebook.exists() or not execution.exists():
            continue
        sizes, seconds = [], 0.0
        for cell in json.loads(notebook.read_text())["cells"]:
            html = "".join(
                "".join(o.get("data", {}).get("text/html", "")) for o in cell.get("outputs", [])
            )
            found = [len(base64.b64decode(m)) for m in VIDEO.findall(html)]
            if found:
                sizes += found
                seconds += cell.get("metadata", {}).get("papermill", {}).get("duration") or 0.0
        wall = json.loads(execution.read_text())["execution_wall_time_s"]
        rows[chapter.name] = {
            "videos": len(sizes),
            "megabytes": [round(b / 1e6, 3) for b in sizes],
            "total_megabytes": round(sum(sizes) / 1e6, 3),
            "video_cells_seconds": round(seconds, 1),
            "page_seconds": wall,
            "share_of_page": round(seconds / wall, 3),
        }
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pages", metavar="SCALE", help="measure the executed pages instead")
    args = parser.parse_args()
    if args.pages:
        rows = page_rows(args.pages)
        out = RESULTS.with_name(f"video_pages_{args.pages}.json")
        write_result(out, {"question": "What each page's videos weigh and cost.", "pages": rows})
        for k, v in rows.items():
            print(k, v)
        return
    missing = renderer_missing()
    robots, frames = ({}, {}) if missing else robot_rows()
    encodings = {}
    for name, clip in page_clips(frames).items():
        video, seconds = timed(lambda: encode(clip, fps=15))
        encodings[name] = {
            "frames": video.frames,
            "size": [video.width, video.height],
            "mime": video.mime,
            "megabytes": round(len(video.data) / 1e6, 3),
            "encode_seconds": round(seconds, 2),
        }
    record = {
        "question": __doc__.splitlines()[0],
        "renderer": "MuJoCo Renderer, MUJOCO_GL=egl (Mesa)" if not missing else missing,
        "robots": robots,
        "encodings": encodings,
    }
    write_result(RESULTS, record)
    for k, v in {**robots, **encodings}.items():
        print(k, v)


if __name__ == "__main__":
    main()
