"""Episodes as videos (qdnb.plotting.video): frames to file and back, the WebP fallback,
the page's output (a numbered, captioned figure), and the frames the chapters draw."""

import base64
import re
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import nbformat
import numpy as np
import pytest

from qdnb.envs.base import Env, EnvState
from qdnb.plotting import FIGURE_KEY
from qdnb.plotting import video as v


def moving_square(t=12, h=40, w=60):
    """A red square crossing a white frame: every frame differs from the last."""
    frames = np.full((t, h, w, 3), 255, np.uint8)
    for i in range(t):
        x = i * (w - 10) // (t - 1)
        frames[i, 15:25, x : x + 10] = (220, 30, 30)
    return frames


def test_frames_round_trip_through_the_encoder_with_their_count_and_size():
    frames = moving_square()
    video = v.encode(frames, fps=10)
    assert video.mime == "video/mp4" and video.data[4:8] == b"ftyp"  # an MP4 container
    assert (video.frames, video.width, video.height) == (12, 60, 40)
    back = v.decode(video)
    assert back.shape == frames.shape
    # lossy, but the square is where it was: the mean error is a few levels of 255
    assert np.abs(back.astype(int) - frames).mean() < 8
    assert back[0, 20, 5, 1] < 100 and back[-1, 20, 5, 1] > 200  # it moved away


def test_odd_sides_are_padded_and_a_video_over_its_budget_is_refused():
    video = v.encode(moving_square(h=41, w=61))
    assert (video.width, video.height) == (62, 42)  # H.264's 4:2:0 colour needs even sides
    noise = np.random.default_rng(0).integers(0, 256, (30, 64, 64, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match="over the 0.00 MB a video may"):
        v.encode(noise, max_bytes=1_000)


def test_without_the_encoder_the_episode_is_an_animated_webp_said_once(monkeypatch, capsys):
    monkeypatch.setattr(v, "encoder", lambda: "imageio-ffmpeg is not usable (test)")
    monkeypatch.setattr(v, "_said_fallback", False)
    frames = moving_square()
    first, second = v.encode(frames), v.encode(frames)
    assert first.mime == "image/webp" and first.data[:4] == b"RIFF"
    assert v.decode(first).shape == frames.shape
    assert capsys.readouterr().out.count("animated WebP") == 1  # said once, not per video
    assert v.video_html(second, b"", "a square").startswith('<img class="qdnb-video"')


def test_scalar_frames_are_coloured_and_clips_play_side_by_side_in_step():
    scalar = np.zeros((3, 4, 5))
    scalar[:, 0, 0] = 2.0
    rgb = v.rgb_frames(scalar, cmap="gray")
    assert rgb.shape == (3, 4, 5, 3) and rgb.dtype == np.uint8
    assert tuple(rgb[0, 0, 0]) == (255, 255, 255) and tuple(rgb[0, 1, 1]) == (0, 0, 0)
    assert v.enlarge(rgb, 3).shape == (3, 12, 15, 3)
    short, tall = moving_square(t=5, h=30), moving_square(t=8, h=40)
    row = v.side_by_side([short, tall], gap=4)
    assert row.shape == (8, 40, 60 + 4 + 60, 3)
    assert np.array_equal(row[7, :30, :60], short[-1])  # the shorter clip holds its last frame
    assert np.all(row[:, 30:, :60] == 255) and np.all(row[:, :, 60:64] == 255)  # white padding
    column = v.one_above_another([short, tall], gap=4)
    assert column.shape == (8, 30 + 4 + 40, 60, 3)
    assert np.array_equal(column[7, :30], short[-1]) and np.all(column[:, 30:34] == 255)
    head = v.titled(tall, "TD3", band=18)
    assert head.shape == (8, 58, 60, 3) and (head[:, :18] < 128).any()  # the title is written
    with pytest.raises(ValueError):
        v.rgb_frames(np.zeros((2, 3)))
    with pytest.raises(ValueError):
        v.side_by_side([])


def test_a_maze_episode_draws_the_point_where_the_path_is():
    path = np.array([[0.0, -0.9], [0.5, -0.9], [0.5, 0.5], [-0.5, 0.8]])
    frames = v.maze_frames(path, size=101, color="#ff0000", every=1)
    assert frames.shape == (4, 101, 101, 3)
    # the last frame's dot sits on the goal: pixel ((x + 1) / 2, (1 - y) / 2) of the image
    col, row = round((-0.5 + 1) / 2 * 100), round((1 - 0.8) / 2 * 100)
    assert tuple(frames[-1, row, col]) == (255, 0, 0)
    assert tuple(frames[0, row, col]) != (255, 0, 0)
    # the walls are drawn (the upper one spans x in [-1, 0.5] at y = 0.2)
    assert tuple(frames[0, round(0.4 * 100), 20]) == (77, 77, 77)
    with pytest.raises(ValueError):
        v.maze_frames(np.zeros((3, 3)))


def test_a_video_is_displayed_as_a_numbered_captioned_figure_of_the_page(monkeypatch):
    from qdnb.book.runner import book_figures

    shown = []
    monkeypatch.setattr(
        "IPython.display.display", lambda data, raw, metadata: shown.append((data, metadata))
    )
    assert (
        v.show_video(moving_square(), "The square crosses.", "A red square.", "fig-square") is None
    )
    ((data, metadata),) = shown
    html = data["text/html"]
    assert re.search(r"<video [^>]*controls loop muted", html) and 'poster="data:image/png' in html
    assert 'type="video/mp4"' in html and 'aria-label="A red square."' in html
    played = base64.b64decode(re.search(r'src="data:video/mp4;base64,([^"]+)"', html)[1])
    # the episode's frames over a white band that keeps the player's controls off them
    band = np.full((12, v.CONTROLS_PX, 60, 3), 255, np.uint8)
    assert played == v.encode(np.concatenate([moving_square(), band], axis=1)).data
    assert "max-width: 100%" in html  # never wider than the column
    assert metadata[FIGURE_KEY] == {
        "caption": "The square crosses.",
        "alt": "A red square.",
        "name": "fig-square",
        "video": True,
    }
    # the book puts it alone in a cell whose MyST-NB options make it a numbered figure
    cell = nbformat.v4.new_code_cell("show_video(...)")
    cell.outputs = [nbformat.v4.new_output("display_data", data=data, metadata=metadata)]
    nb = nbformat.v4.new_notebook()
    nb.cells = [cell]
    book_figures(nb)
    figure = nb.cells[1].metadata["mystnb"]["figure"]
    assert figure == {"caption": "The square crosses.", "name": "fig-square"}
    with pytest.raises(ValueError, match="caption and an alt text"):
        v.show_video(moving_square(), " ", "alt")
    with pytest.raises(ValueError, match="does not fit the page's column"):
        v.show_video(moving_square(w=700), "caption", "alt")


class Core(NamedTuple):
    q: jax.Array


@dataclass(frozen=True)
class Slider(Env):
    """Slides by its action each step and is done once past 2.5; the scan keeps stepping
    it to ``episode_length``, so it slides on past its end. Its core holds ``q``, as a
    brax state does."""

    episode_length: int = 6
    observation_size: int = 1
    action_size: int = 1
    descriptor_size: int = 1
    descriptor_low: tuple[float, ...] = (-10.0,)
    descriptor_high: tuple[float, ...] = (10.0,)

    def reset(self, key):
        q = jnp.zeros(1)
        return EnvState(Core(q), q, jnp.zeros(()), jnp.zeros((), bool), q, jnp.int32(0))

    def step(self, state, action):
        q = state.core.q + action
        return EnvState(Core(q), q, jnp.zeros(()), q[0] > 2.5, q, state.steps + 1)


@dataclass(frozen=True)
class KeyedSlider(Slider):
    """A ``Slider`` starting where its key draws it, described by its mean position over
    the states its steps started from (a time-averaged descriptor)."""

    def reset(self, key):
        q = jax.random.uniform(key, (1,), minval=-1.0, maxval=1.0)
        return EnvState(Core(q), q, jnp.zeros(()), jnp.zeros((), bool), q, jnp.int32(0))

    def behaviour_descriptor(self, last_state_descriptor, state_descriptor_sum, length):
        return state_descriptor_sum / jnp.maximum(length, 1)


def test_an_episode_path_holds_its_last_state_once_the_episode_has_ended():
    from qdnb.envs.render import episode_path

    # one step a step: done at its third, held for the three after
    path = episode_path(Slider(6), lambda params, obs: params, jnp.ones(1), jax.random.PRNGKey(0))
    assert path[:, 0].tolist() == [0, 1, 2, 3, 3, 3, 3]  # the reset state, three steps, held


def test_robot_states_are_held_once_an_episode_ends_and_drawn_from_the_model():
    from qdnb.envs.render import episode_states, renderer_missing

    speeds = jnp.array([[1.0], [0.5]])  # two policies: the first ends at its third step
    qs, alive = episode_states(
        Slider(5), lambda p, obs: p, speeds, jax.random.split(jax.random.PRNGKey(0), 2)
    )
    assert qs[0, :, 0].tolist() == [0, 1, 2, 3, 3, 3] and alive[0].tolist() == [1, 1, 1, 0, 0, 0]
    assert qs[1, :, 0].tolist() == [0, 0.5, 1, 1.5, 2, 2.5] and alive[1].all()
    if renderer_missing() is None:  # the Ant drawn from its MuJoCo model: not a blank image
        from qdnb.envs import make_env
        from qdnb.envs.render import Camera, render

        env = make_env("ant_omni")
        q0 = np.asarray(env.reset(jax.random.PRNGKey(0)).core.q)
        frames = render(env, np.stack([q0, q0 + 0.3]), width=64, height=48, camera=Camera())
        assert frames.shape == (2, 48, 64, 3) and frames.std() > 10
        assert not np.array_equal(frames[0], frames[1])  # the robot moved
        marked = render(env, q0[None], 64, 48, Camera(), marks=((0.8, 0.0),))
        red = (marked[0, ..., 0] > 150) & (marked[0, ..., 1] < 80) & (marked[0, ..., 2] < 80)
        assert red.any() and not np.array_equal(marked[0], frames[0])  # the disc is drawn


def test_recorded_actions_replay_step_by_step_and_are_held_once_the_episode_ends():
    from qdnb.envs.render import replay_states

    actions = jnp.array([[[1.0], [0.5], [2.0], [1.0], [1.0]], [[0.1], [0.2], [0.3], [0.4], [0.5]]])
    qs, alive = replay_states(Slider(5), actions, jax.random.split(jax.random.PRNGKey(0), 2))
    assert qs.shape == (2, 6, 1)
    assert qs[0, :, 0].tolist() == [0, 1, 1.5, 3.5, 3.5, 3.5]  # done past 2.5 at step 3: held
    assert alive[0].tolist() == [1, 1, 1, 0, 0, 0]
    assert np.allclose(qs[1, :, 0], [0, 0.1, 0.3, 0.6, 1.0, 1.5]) and alive[1].all()


def test_a_watched_episode_is_the_evaluated_one_with_its_states_and_its_descriptor():
    from qdnb.envs.render import episode_states, watched_episodes
    from qdnb.envs.rollout import evaluate_policies

    speeds, key = jnp.array([[1.0], [0.5], [-0.75]]), jax.random.PRNGKey(3)
    apply = lambda p, obs: p  # noqa: E731
    qs, reached = watched_episodes(Slider(5), apply, speeds, jax.random.split(key, 3))
    alone, _ = episode_states(Slider(5), apply, speeds, jax.random.split(key, 3))
    evaluated = evaluate_policies(Slider(5), apply, speeds, key)  # starts: split(key, 3)
    assert np.array_equal(qs, alone)
    # the first ends past 2.5 at its third step, the others play all five
    assert reached[:, 0].tolist() == [3.0, 2.5, -3.75]
    assert np.array_equal(reached, np.asarray(evaluated.descriptor))
    # starts drawn from the keys, and a time-averaged descriptor: still the evaluated ones
    keyed = KeyedSlider(5)
    qs, reached = watched_episodes(keyed, apply, speeds, jax.random.split(key, 3))
    evaluated = evaluate_policies(keyed, apply, speeds, key)
    assert len(set(qs[:, 0, 0].tolist())) == 3  # three different starts
    np.testing.assert_allclose(reached, np.asarray(evaluated.descriptor), rtol=1e-6)
    assert not np.allclose(reached[:, 0], qs[:, -1, 0])  # an average, not the last state


def test_a_mark_keeps_its_size_on_screen_as_the_camera_backs_away():
    from qdnb.envs.render import renderer_missing

    if renderer_missing() is not None:
        pytest.skip(renderer_missing())
    from qdnb.envs import make_env
    from qdnb.envs.render import Camera, render

    env = make_env("ant_omni")
    q0 = np.asarray(env.reset(jax.random.PRNGKey(0)).core.q)

    def red_pixels(distance, **kw):
        camera = Camera(distance=distance, elevation=-89.0, lookat=(0.0, 0.0, 0.0))
        frame = render(env, q0[None], 80, 80, camera, marks=((distance / 5, 0.0),), **kw)[0]
        r, g, b = np.moveaxis(frame.astype(int), -1, 0)
        return int(((r > g + 60) & (r > b + 60)).sum())  # red, however lit

    near, far = red_pixels(4.0), red_pixels(16.0)
    assert near > 0 and 0.5 < far / near < 2.0  # the default radius follows the distance
    assert red_pixels(16.0, mark_radius=0.2) < far / 4  # a fixed radius shrinks on screen
    camera = Camera(distance=40.0, elevation=-89.0, lookat=(0.0, 0.0, 0.0))
    r, g, b = np.moveaxis(
        render(env, q0[None], 80, 80, camera, torso_mark=True)[0].astype(int), -1, 0
    )
    blue = (b > r + 60) & (b > g + 60)
    rows, cols = np.nonzero(blue)
    assert blue.any() and abs(rows.mean() - 40) < 6 and abs(cols.mean() - 40) < 6  # under the torso
    with pytest.raises(ValueError, match="mark_radius"):
        render(env, q0[None], 8, 8, Camera(), marks=((0.0, 0.0),), mark_radius=0.0)


def test_flat_clips_names_the_clips_that_play_in_one_colour():
    """As drawn on [0, top]: a constant clip and one beyond the scale (all its top colour)
    are flat; a clip spanning the scale is not; the shared first frame counts on request."""
    first = np.zeros((1, 4, 4))
    moving = np.concatenate([first, np.linspace(0, 1, 32).reshape(2, 4, 4)])
    still = np.concatenate([first, np.full((2, 4, 4), 0.5)])
    beyond = np.concatenate([first, np.full((2, 4, 4), 3.0)])
    assert v.flat_clips({"a": moving, "b": still, "c": beyond}, top=1.0) == ["b", "c"]
    assert v.flat_clips({"b": still}, top=1.0, first_shared=False) == []


def test_locomotion_camera_keeps_every_point_in_view_of_ant_omni():
    from qdnb.envs.render import locomotion_camera

    far = locomotion_camera("ant_omni", [[3.0, -4.0], [1.0, 0.5]])
    assert far.distance == pytest.approx(2.4 * 5.0) and far.lookat == (0.0, 0.0, 0.0)
    assert locomotion_camera("ant_omni").distance == pytest.approx(2.4 * 2.0)  # 2 m at least
    assert locomotion_camera("halfcheetah_uni").lookat is None  # follows the torso
    with pytest.raises(ValueError, match="ant_omni, halfcheetah_uni"):
        locomotion_camera("pointmaze")


def test_the_drawn_floor_is_wider_with_checkers_as_large():
    """A Halfcheetah leaves Brax's 80 m floor in a long episode: the model drawn has its
    floor ten times wider, the texture repeated ten times more, the simulated one intact."""
    import mujoco

    from qdnb.envs import make_env
    from qdnb.envs.render import FLOOR_SCALE, _drawn_model

    model = make_env("halfcheetah_uni", episode_length=10).brax_env.sys.mj_model
    drawn = _drawn_model(model)
    floor = np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)[0]
    material = model.geom_matid[floor]
    np.testing.assert_allclose(drawn.geom_size[floor, :2], FLOOR_SCALE * model.geom_size[floor, :2])
    np.testing.assert_allclose(
        drawn.mat_texrepeat[material] / drawn.geom_size[floor, :2],
        model.mat_texrepeat[material] / model.geom_size[floor, :2],
    )
    assert model.geom_size[floor, 0] == 40.0  # the simulated model is left as it was
