"""What a reader sees: tables printed as a paper prints them, figures that fit the
column with a caption and alt text, and the page's figure cells."""

import math

import matplotlib
import nbformat
import numpy as np
import pandas as pd
import pytest
from notebook_runs import write_notebook

matplotlib.use("Agg")

from qdnb.book import runner  # noqa: E402
from qdnb.core.names import mean_sd  # noqa: E402
from qdnb.plotting import COLUMN_INCHES, FIGURE_KEY, show  # noqa: E402
from qdnb.plotting.tables import cell_html, cell_text, styled  # noqa: E402


def test_a_table_has_no_default_index_rounds_and_writes_everything_out():
    df = pd.DataFrame(
        {
            "environment": ["ant_omni", "halfcheetah_uni"],
            "value": [np.float32(-26.540001), math.nan],
            "holds": [True, False],
            "settings": [{"lr": 0.001, "steps": 300}, None],
            "note": ["x" * 120, ""],
        }
    )
    html = styled(df)
    assert "<th>0</th>" not in html and ">0<" not in html  # no 0, 1, 2... index
    assert ">-26.54<" in html and "-26.540001" not in html
    assert html.count(">—<") == 3  # NaN, None and the empty string
    assert ">✓<" in html and ">✗<" in html
    assert "x" * 120 in html and "..." not in html  # nothing cut
    assert "lr: 0.001, steps: 300" in html
    assert ">Ant-Omni<" in html and ">Halfcheetah-Uni<" in html and "ant_omni" not in html
    # a meaningful index stays, as row labels
    named = styled(pd.DataFrame({"a": [1.0]}, index=pd.Index(["ME"], name="method")))
    assert "<th>method</th>" in named and "<th>ME</th>" in named


def test_identifiers_are_code_long_labels_wrap_and_only_a_dump_may_scroll():
    df = pd.DataFrame(
        {"num_seeds": [2], "source": ["config (agac_torch/configs/point_maze.yaml)"]},
        index=pd.Index(["QD-PG, Adam (the A/B's base reading)"], name="reading"),
    )
    html = styled(df)
    assert "<th><code>num_seeds</code></th>" in html
    assert "config (<code>agac_torch/configs/point_maze.yaml</code>)" in html
    assert '<th class="long">' in html and 'class="qdnb-table"' in html
    assert "<th>ME</th>" in styled(pd.DataFrame({"a": [1]}, index=pd.Index(["ME"], name="m")))
    assert cell_html({"lr_actor": 3e-4, "steps": 10}) == "<code>lr_actor</code>: 0.0003, steps: 10"
    assert 'class="qdnb-table qdnb-dump"' in styled(df, dump=True)
    assert cell_html(["num_seeds", 2.5]) == "<code>num_seeds</code>, 2.5"
    assert cell_html({"ant_omni": 1}) == "Ant-Omni: 1"  # a key the reader has a name for
    # a Markdown code span in a cell is code, as in the text; a lone backtick stays one
    assert cell_html("ran (no verdict at `tiny`)") == "ran (no verdict at <code>tiny</code>)"
    assert cell_html("a ` b") == "a ` b"


def test_a_mean_over_one_seed_has_no_spread_and_diverged_seeds_are_counted():
    assert mean_sd([-126.04]) == "-126.0 (1 seed)"
    assert mean_sd([1.0, 3.0], digits=2) == "2.00 ± 1.00 (2 seeds)"
    assert mean_sd([1.0, 3.0, np.nan]) == "2.0 ± 1.0 (2 seeds), 1 diverged"
    assert mean_sd([np.nan]) == "diverged" and mean_sd([]) == "—"
    assert mean_sd([1500.0, 1580.0], digits=0) == "1,540 ± 40 (2 seeds)"  # thousands separated


def test_machine_written_words_become_a_readers():
    from qdnb.core.names import markdown_words

    assert markdown_words("ant_omni ME: start") == "Ant-Omni ME: start"
    assert markdown_words("rate from qdt_h100_paper on x86_64") == (
        "rate from `qdt_h100_paper` on `x86_64`"
    )
    assert markdown_words("already `ch3_qdpg`, halfcheetah_uni") == (
        "already `ch3_qdpg`, Halfcheetah-Uni"
    )
    # code spans, paths, links and addresses stay as they are
    for kept in ("`data/qdt/ant_omni.npz`", "[docs](https://x.org/a_b)", "see https://x.org/a_b"):
        assert markdown_words(kept) == kept
    assert markdown_words("data/runs/small/antmaze/x.npz") == "data/runs/small/antmaze/x.npz"


def test_the_sidebar_groups_the_pages_by_the_thesiss_chapters():
    import yaml

    from qdnb.book import registry

    toc = yaml.safe_load(registry.toc())
    captions = [p["caption"] for p in toc["parts"]]
    assert [c.split(" ·")[0] for c in captions] == [
        "Chapters 1–2",
        "Chapter 3",
        "Chapter 4",
        "Chapter 5",
        "About this book",
    ]
    ch3 = [c["file"] for c in toc["parts"][1]["chapters"]]
    assert ch3 == [
        "chapters/ch3_qdpg",
        "chapters/ch3_baselines",
        "chapters/ch3_evolution",
        "chapters/ch3_how",  # each thesis chapter closes with how it was run
    ]
    files = [c["file"] for p in toc["parts"] for c in p["chapters"]]
    assert files[-3:] == ["reproducing", "paper_scale", "references"]
    assert len(files) == len(registry.CHAPTERS) + len(registry.APPENDICES) + 3
    # one name per page everywhere: the registry's title (the status table, the paper page)
    # is the notebook's heading (the page and the sidebar)
    for chapter in registry.CHAPTERS:
        nb = nbformat.read(chapter.notebook, as_version=4)
        heading = next(
            line[2:]
            for c in nb.cells
            if c.cell_type == "markdown"
            for line in c.source.splitlines()
            if line.startswith("# ")
        )
        assert heading == chapter.title, chapter.name


def test_cells_tagged_for_the_appendix_leave_the_page_for_their_chapters_appendix():
    from qdnb.book import appendix, registry

    nb = nbformat.v4.new_notebook()
    nb.cells = [
        nbformat.v4.new_markdown_cell("# Title\n\nThe story."),
        nbformat.v4.new_markdown_cell(
            "## Budget rule\n\n### Detail", metadata={"tags": ["appendix"]}
        ),
        nbformat.v4.new_code_cell("x = 1", metadata={"tags": ["hide-input", "appendix"]}),
        nbformat.v4.new_markdown_cell("## Results"),
    ]
    moved = appendix.split(nb)
    assert [c.source for c in nb.cells] == ["# Title\n\nThe story.", "## Results"]
    assert [c.source for c in moved] == ["## Budget rule\n\n### Detail", "x = 1"]
    ch3 = registry.chapter("ch3_qdpg")
    page = appendix.page(ch3.part, [(ch3, moved)], "tiny", nb.metadata)
    title, section, heading, code = page.cells
    assert title.source.startswith("# How Chapter 3 was run") and "`tiny`" in title.source
    assert section.source.startswith(f"## {ch3.title}") and "(ch3_qdpg)" in section.source
    # the moved headings sit under their page's section
    assert heading.source == "### Budget rule\n\n#### Detail" and code.source == "x = 1"
    again = nbformat.v4.new_markdown_cell("#### Deep\n\ntext", metadata={"tags": ["appendix"]})
    assert appendix._demoted(again).source == "### Deep\n\ntext"
    assert "(ch3_how)" in appendix.link(ch3)


def test_degenerate_figures_are_found_and_never_shown_silently(monkeypatch):
    import matplotlib.pyplot as plt

    from qdnb import plotting

    fig, axs = plt.subplots(1, 4, figsize=(6, 2))
    fig.colorbar(axs[0].imshow(np.full((4, 4), 0.3)), ax=axs[0])
    axs[1].plot([np.nan, np.nan])
    axs[1].set_title("loss")
    axs[2].plot([0], [2.0])  # a curve of one point: one evaluation
    axs[3].imshow(np.random.default_rng(0).random((3, 3)))  # a real image, and lines of
    axs[3].plot([0, 1], [0, 1])  # two points, a marker and a reference line are fine
    axs[3].plot([0.5], [0.5], "o")
    axs[3].axhline(0.2)
    assert plotting.degeneracies(fig) == [
        "panel 1 is a uniform image (0.3)",
        "panel 2 (loss) has no finite value to draw",
        "panel 3 draws each curve as a single point",
        "a colour bar spans a single value (0.3)",
    ]
    other, axs = plt.subplots(1, 3, figsize=(6, 2))  # masked points are not data; words are
    axs[0].plot(np.ma.masked_array([1.0, 2.0, 3.0], [True, True, False]))
    axs[1].plot(["a", "b"], [1, 2])
    axs[2].plot([0, 1], ["x", "y"])
    assert plotting.degeneracies(other) == ["panel 1 draws each curve as a single point"]
    plt.close(other)
    # a prediction drawn on the true frame's colour scale, wholly above it: one colour
    beyond, axs = plt.subplots(1, 2, figsize=(4, 2))
    axs[0].imshow(np.linspace(2.0, 5.0, 9).reshape(3, 3), vmin=0, vmax=1)
    axs[1].imshow(np.linspace(0.5, 5.0, 9).reshape(3, 3), vmin=0, vmax=1)  # partly inside
    assert plotting.degeneracies(beyond) == [
        "panel 1 is drawn in one colour: its values (2 to 5) lie beyond its colour scale (0 to 1)"
    ]
    plt.close(beyond)
    beyond, axs = plt.subplots(1, 3, figsize=(4, 2))
    for ax in axs:
        ax.imshow(np.linspace(2.0, 5.0, 9).reshape(3, 3), vmin=0, vmax=1)
    assert plotting.degeneracies(beyond) == [
        "panels 1, 2 and 3 are drawn in one colour: their values lie beyond their colour "
        "scales (2 to 5 against 0 to 1 in the first)"
    ]
    plt.close(beyond)
    shown = []
    monkeypatch.setattr("IPython.display.display", lambda obj, **kw: shown.append(kw))
    show(fig, "Losses.", "Four panels.")
    caption = shown[-1]["metadata"][FIGURE_KEY]["caption"]
    assert caption.startswith("Losses. **Degenerate at this scale:** panel 1 is a uniform")
    assert caption.endswith("(no reason given)")
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.imshow(np.zeros((2, 2)))
    show(fig, "A frame.", "A frame.", note="At tiny the FLT predicts the mean frame.")
    assert shown[-1]["metadata"][FIGURE_KEY]["caption"].endswith(
        "uniform image (0). At tiny the FLT predicts the mean frame."
    )
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1, 2], [3, 1, 2])
    show(fig, "A curve.", "A curve.")
    assert shown[-1]["metadata"][FIGURE_KEY]["caption"] == "A curve."


def test_numbers_print_in_one_style_to_four_significant_digits_in_tables():
    from qdnb.core.names import majority_text, number_text, seeds_text

    assert [cell_text(v) for v in (0.123456, 123456.7, 8.4e7, 2e-5, 12, 8000, 120_000)] == [
        "0.1235",
        "1.235·10⁵",
        "8.4·10⁷",
        "2·10⁻⁵",
        "12",
        "8,000",
        "120,000",
    ]
    assert cell_text(np.inf) == "∞" and cell_text([1.0, 2.5]) == "1, 2.5"
    # in text, two significant figures: separators to 99,999, then powers of ten as the thesis
    # prints them; never "1.6e+04" or "inf"
    assert [number_text(v) for v in (16_384.0, 8_000, 1e6, 1.6e6, 3e10, -126.04, 0.0035)] == [
        "16,000",
        "8,000",
        "10⁶",
        "1.6·10⁶",
        "3·10¹⁰",
        "-130",
        "0.0035",
    ]
    assert number_text(float("inf")) == "∞" and number_text(float("nan")) == "—"
    assert [seeds_text(1), seeds_text(4), seeds_text(2, "goal")] == ["1 seed", "4 seeds", "2 goals"]
    assert majority_text(1) == "on its one seed"
    from qdnb.core.names import over_seeds_text

    assert (
        over_seeds_text(1) == "one seed" and over_seeds_text(3) == "mean over 3 seeds, range shaded"
    )
    assert over_seeds_text(2, "") == "mean over 2 seeds"
    # a recorded device in a reader's words; text in no known form is left as it is
    from qdnb.core.names import machine_text

    assert machine_text("cpu: cpu x2 (2 CPU cores, AMD EPYC)") == "2 CPU cores (AMD EPYC)"
    assert machine_text("cpu: cpu x1 (2 CPU cores)") == "2 CPU cores"
    assert machine_text("gpu: NVIDIA H100 x1 (16 CPU cores, Xeon)") == (
        "1 NVIDIA H100 (beside 16 CPU cores, Xeon)"
    )
    assert machine_text("a laptop") == "a laptop"
    assert majority_text(3) == "on the mean over 3 seeds and on most of them"


def test_legends_move_off_the_data_and_never_onto_another_panel():
    import matplotlib.pyplot as plt

    from qdnb.plotting import clear_legends, legend_overlaps, panel_grid

    rng = np.random.default_rng(0)
    # a curve under the legend's corner: it moves inside the panel, off the curve
    fig, ax = plt.subplots(figsize=(4, 3))
    x = np.linspace(0, 1, 200)
    ax.plot(x, 0.9 + 0.1 * x, label="high")
    ax.plot(x, x, label="rising")
    ax.legend(loc="upper left")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    assert legend_overlaps(ax, renderer) > 0
    clear_legends(fig)
    fig.canvas.draw()
    assert legend_overlaps(ax, renderer) == 0
    plt.close(fig)
    # a panel full of points: the legend goes below it, under its axis label
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.scatter(rng.random(3000), rng.random(3000), s=2, label="points")
    ax.set_xlabel("x")
    ax.legend(loc="upper right")
    clear_legends(fig)
    fig.canvas.draw()
    assert legend_overlaps(ax, renderer := fig.canvas.get_renderer()) == 0
    assert ax.get_legend().get_window_extent(renderer).y1 < ax.xaxis.label.get_window_extent().y0
    plt.close(fig)
    # a legend its maker put outside the panel stays there, whatever the panel clips away
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.plot(x, 3 * x - 2, label="leaves the panel below")
    ax.set_ylim(0, 1)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.15))
    clear_legends(fig)
    assert ax.get_legend()._loc == 9 and ax.get_legend().get_bbox_to_anchor().y0 < ax.bbox.y0
    plt.close(fig)
    # ... unless another panel lies there: then it stays inside, where it covers least; a
    # hidden slot of the grid is no panel
    fig, axes = panel_grid(3, ncols=2, aspect=0.75)  # 2 x 2, the last slot hidden
    for a in axes[:3]:
        a.scatter(rng.random(3000), rng.random(3000), s=2, label="points")
        a.set_xlabel("x")
        a.legend(loc="upper right")
    clear_legends(fig)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    first, second = (a.get_legend().get_window_extent(renderer) for a in axes[:2])
    assert not first.overlaps(axes[2].get_tightbbox(renderer))  # kept inside the top left
    assert second.y1 < axes[1].xaxis.label.get_window_extent().y0  # below, over the hidden slot
    plt.close(fig)


def test_arrows_count_as_data_a_legend_moves_off():
    import matplotlib.pyplot as plt

    from qdnb.plotting import clear_legends, legend_overlaps, reward_arrows

    fig, ax = plt.subplots(figsize=(4, 3))
    reward_arrows(ax, (0.9, 0.9), (0, 0), (1, 1), n=15)  # arrows over the whole panel
    ax.scatter([0.1], [0.1], label="start")
    ax.legend(loc="upper left")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    assert legend_overlaps(ax, renderer) > 0  # the arrows' tails under the legend count
    clear_legends(fig)
    fig.canvas.draw()
    assert legend_overlaps(ax, renderer) == 0
    plt.close(fig)


def test_a_legend_entry_whose_curve_cannot_be_seen_says_why():
    import matplotlib.pyplot as plt

    from qdnb.plotting import name_unseen_lines

    fig, ax = plt.subplots(figsize=(4, 3))
    x = np.arange(10.0)
    ax.plot(x, 1 + x, label="NSR-ES")
    ax.plot(x, 1 + x, label="NSRA-ES")  # drawn after, exactly over NSR-ES
    ax.plot(x, 2 + x, label="ME-ES")
    ax.plot(x, 30 + x, label="ES")
    ax.plot(x, 30.001 + x, label="ES, again")  # a hair apart: still under it on the page
    ax.plot(x, 10 + x, label="far apart")
    ax.plot(x, 13 + x, label="above far apart")  # visibly apart: both seen
    ax.axhline(0.0, ls=":", label="replay floor")  # zero: a log axis cannot place it
    ax.set_yscale("log")
    ax.plot(x, 1e6 + x, label="far")
    ax.set_ylim(0.5, 100)  # ... and "far" lies above the panel
    ax.legend()
    name_unseen_lines(fig)
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert texts == [
        "NSR-ES (under NSRA-ES)",
        "NSRA-ES",
        "ME-ES",
        "ES (under ES, again)",
        "ES, again",
        "far apart",
        "above far apart",
        "replay floor (at 0, off the log scale)",
        "far (outside the panel)",
    ]
    plt.close(fig)


def test_tick_labels_that_collide_are_thinned_and_hand_placed_ones_stay():
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MultipleLocator

    from qdnb.plotting import _labels_collide, integer_axes, thin_ticks

    fig, (ax, named) = plt.subplots(1, 2, figsize=(4, 2))
    ax.plot(np.arange(0, 8001, 800), np.arange(11))
    ax.set_xlabel("environment steps")
    ax.xaxis.set_major_locator(MultipleLocator(800))  # 11 long labels in a narrow panel
    named.bar(range(6), np.ones(6))
    named.set_xticks(range(6), [f"method {i}" for i in range(6)])  # collide, but by hand
    integer_axes(fig)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    assert _labels_collide(ax.xaxis, renderer) and _labels_collide(named.xaxis, renderer)
    thin_ticks(fig)
    fig.canvas.draw()
    assert not _labels_collide(ax.xaxis, renderer)
    ticks = ax.get_xticks()
    assert 2 <= len(ticks) < 11 and np.allclose(ticks, np.round(ticks))  # still integers
    assert [t.get_text() for t in named.get_xticklabels()] == [f"method {i}" for i in range(6)]
    plt.close(fig)


def test_axes_that_count_iterations_or_epochs_have_integer_ticks():
    import matplotlib.pyplot as plt

    from qdnb.plotting import integer_axes

    fig, ax = plt.subplots(figsize=(3, 2))
    bar = fig.colorbar(ax.scatter([0, 1], [0, 1], c=[0, 2]), ax=ax, label="iteration")
    ax.plot([0, 3], [0, 1])
    ax.set(xlabel="epoch", ylabel="distance")
    integer_axes(fig)
    fig.canvas.draw()
    assert all(float(t).is_integer() for t in bar.ax.get_yticks())  # not 0.00, 0.25, ...
    assert all(float(t).is_integer() for t in ax.get_xticks())
    assert not all(float(t).is_integer() for t in ax.get_yticks())  # a distance is no count
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(3, 2))  # a count of trajectories per cell
    bar = fig.colorbar(ax.imshow([[0, 3]]), ax=ax, label="trajectories")
    integer_axes(fig)
    fig.canvas.draw()
    assert all(float(t).is_integer() for t in bar.ax.get_yticks())  # not 0.5, 1.5, ...
    plt.close(fig)


def test_a_figure_wider_than_the_column_or_without_caption_is_refused():
    import matplotlib.pyplot as plt

    with pytest.raises(ValueError, match="does not fit the page's column"):
        show(plt.figure(figsize=(COLUMN_INCHES + 1, 3)), "a caption", "an alt text")
    with pytest.raises(ValueError, match="caption and an alt text"):
        show(plt.figure(figsize=(4, 3)), "", "an alt text")


def test_a_shown_figure_becomes_a_captioned_figure_of_the_page(tmp_path):
    src = write_notebook(
        tmp_path / "figure.ipynb",
        (
            "import matplotlib.pyplot as plt\n"
            "import pandas as pd\n"
            "from IPython.display import display\n"
            "from qdnb.plotting import set_style, show\n"
            "set_style()\n"
            "display(pd.DataFrame({'a': [1.23456]}))\n"
            "fig, ax = plt.subplots(figsize=(4, 3))\n"
            "ax.plot([0, 1])\n"
            "show(fig, 'A line, $y = x$.', 'A rising line.', 'fig-line')\n"
            "print('after the figure')",
            ["hide-input"],
        ),
    )
    out = runner.execute(src, tmp_path / "out" / "figure.ipynb", {"scale": "tiny"}, "f", False)
    executed = nbformat.read(out, as_version=4)
    outputs = executed.cells[-1].outputs
    png = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(png) == 1 and png[0]["metadata"][FIGURE_KEY]["caption"] == "A line, $y = x$."
    # drawn at twice the size it is shown at: 200 dpi, 4 x 3 inches shown at 400 px or less
    assert png[0]["metadata"]["image/png"]["width"] <= 400
    assert "1.235" in outputs[0]["data"]["text/html"]  # the book's table
    runner.book_figures(executed)
    source, figure, rest = executed.cells[-3:]
    assert source.metadata["tags"] == ["hide-input"] and len(source.outputs) == 1  # the table
    assert figure.metadata["tags"] == ["remove-input"] and figure.source.startswith("#")
    assert figure.metadata["mystnb"] == {
        "figure": {"caption": "A line, $y = x$.", "name": "fig-line"},
        "image": {"alt": "A rising line."},
    }
    assert [o["output_type"] for o in rest.outputs] == ["stream"]
    assert rest.outputs[0]["text"] == "after the figure\n"


def test_tick_labels_print_in_the_books_style_not_against_an_offset():
    import matplotlib.pyplot as plt

    from qdnb.plotting import plain_tick_labels

    with plt.rc_context({"axes.formatter.limits": (-3, 4)}):  # set_style's
        fig, axes = plt.subplots(1, 3, figsize=(6, 2))
        axes[0].plot([0, 400_000], [0, 1])  # Matplotlib: 0 ... 4 and "1e5" at the end
        axes[1].plot([1000.1, 1000.5], [0, 1])  # "+1e3", an added offset: left alone
        axes[2].plot([0, 1], [0, 1])  # no offset: Matplotlib's labels stay
        plain_tick_labels(fig)
        fig.canvas.draw()
    labels = [t.get_text() for t in axes[0].get_xticklabels() if t.get_text()]
    assert "2·10⁵" in labels and "0" in labels and axes[0].xaxis.get_offset_text().get_text() == ""
    for ax in axes[1:]:
        assert type(ax.xaxis.get_major_formatter()).__name__ == "ScalarFormatter"
    plt.close(fig)


def test_a_log_axis_shorter_than_a_decade_gets_labelled_ticks():
    import matplotlib.pyplot as plt

    from qdnb.plotting import log_ticks

    fig, axes = plt.subplots(1, 2, figsize=(6, 2))
    axes[0].plot([2_000, 30_000], [0, 1])  # one power of ten (10⁴) inside: one label
    axes[0].set_xscale("log")
    axes[1].plot([1, 1e6], [0, 1])  # six decades: Matplotlib's ticks stay
    axes[1].set_xscale("log")
    log_ticks(fig)
    fig.canvas.draw()
    low, high = axes[0].get_xlim()
    labels = [
        t.get_text() for t, v in zip(axes[0].get_xticklabels(), axes[0].get_xticks())
        if low <= v <= high
    ]  # fmt: skip
    assert labels == ["2,000", "5,000", "10,000", "20,000"]
    assert type(axes[1].xaxis.get_major_locator()).__name__ == "LogLocator"
    assert axes[1].xaxis.get_major_locator()._subs.tolist() == [1.0]
    plt.close(fig)
