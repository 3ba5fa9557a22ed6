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
from qdnb.plotting import COLUMN_INCHES, FIGURE_KEY, show  # noqa: E402
from qdnb.plotting.tables import cell_text, styled  # noqa: E402


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


def test_numbers_print_to_four_significant_digits():
    assert [cell_text(v) for v in (0.123456, 123456.7, 8.4e7, 2e-5, 12, 120_000)] == [
        "0.1235",
        "1.235e5",
        "8.4e7",
        "2e-5",
        "12",
        "120,000",
    ]
    assert cell_text(np.inf) == "∞" and cell_text([1.0, 2.5]) == "1, 2.5"


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
