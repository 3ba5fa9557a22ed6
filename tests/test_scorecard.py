"""The claims scorecard and the chapter boxes, read from hand-made summaries."""

import json

from finished_runs import write_run

from qdnb.book import runner, scorecard
from qdnb.core import claims, paths

HOLDS, FAILS, CANNOT = (scorecard.SYMBOL[k] for k in ("holds", "fails", "cannot show"))


def write_summary(scale, name, records, wall=12.0):
    write_run(scale, name, {"headline": "h", "claims": records}, wall_time_s=wall)


def test_the_scorecard_lists_each_claim_by_scale_with_its_numbers(runs):
    a = claims.record("ch5/flt", "The FLT beats the mean frame", False, "0.38 vs 0.0035")
    write_summary("tiny", "ch5_flow_lenia", [a])
    write_summary("small", "ch5_flow_lenia", [{**a, "status": "holds", "numbers": "0.01 vs 0.02"}])
    write_summary(
        "tiny", "ch3_evolution", [claims.record("e", "QD-PG is faster", "cannot show", "")]
    )
    table = scorecard.scorecard(scorecard.summaries())
    (row,) = [line for line in table.splitlines() if "The FLT beats" in line]
    cells = [c.strip() for c in row.split(" | ")]
    # at tiny a check ran, no verdict is printed; at small it is the verdict
    assert cells[2].startswith(scorecard.RAN) and "0.38 vs 0.0035" in cells[2]
    assert FAILS not in table.split("The FLT beats")[1].split("\n")[0]
    assert cells[3].startswith(HOLDS) and "0.01 vs 0.02" in cells[3]
    assert cells[4].rstrip(" |") == scorecard.NOT_RUN  # no paper run
    assert any("QD-PG is faster" in r and scorecard.RAN in r for r in table.splitlines())
    # a page with no run at any scale still has its row
    assert "*no claim recorded yet*" in table and "[Ch. 4: the QDT](chapters/ch4_qdt)" in table
    tally = scorecard.tally(scorecard.summaries())
    assert "**`tiny`**" in tally and "2 claim checks ran" in tally and "no verdict" in tally
    assert "1 of 1 claim holds, 0 fail, 0 cannot show" in tally  # small
    assert "**`paper`**: not run" in tally


def test_a_page_opens_with_its_claims_and_at_tiny_a_warning(runs):
    write_summary("tiny", "ch2_primer", [claims.record("ch2/goal", "NS reaches", False, "0/2")])
    box = scorecard.chapter_box(
        "ch2_primer",
        "tiny",
        json.loads((paths.run_dir("tiny", "ch2_primer") / "summary.json").read_text()),
    )
    assert box.startswith("````{admonition} At a glance") and ":class: warning" in box
    assert "code-path check only" in box and "not evidence" in box
    assert f"| NS reaches | {scorecard.RAN} | 0/2 |" in box and "12 s" in box and "2 CPU" in box
    assert FAILS not in box  # no verdict at tiny
    write_summary("small", "ch2_primer", [claims.record("ch2/goal", "NS reaches", False, "0/2")])
    ran = json.loads((paths.run_dir("small", "ch2_primer") / "summary.json").read_text())
    assert f"| NS reaches | {FAILS} | 0/2 |" in scorecard.chapter_box("ch2_primer", "small", ran)
    small = scorecard.chapter_box("ch2_primer", "small", None)
    assert ":class: note" in small and "not evidence" not in small and "no run record" in small
    status = runner.status_table("tiny")
    assert "ran at scale tiny" in status and f"| NS reaches | {scorecard.RAN}<br>" in status


def test_a_page_prints_verdicts_only_at_a_scale_that_is_evidence():
    import pandas as pd

    checks = pd.DataFrame({"claim": ["a", "b"], "holds": [True, False]})
    small = scorecard.verdict_column(checks, "small")
    assert list(small["verdict"]) == [HOLDS, FAILS] and "holds" not in small
    tiny = scorecard.verdict_column(checks, "tiny")
    assert set(tiny["verdict"]) == {scorecard.RAN}  # no ✓ / ✗ from noise
    assert scorecard.verdict("cannot show", "small").startswith("—")
    assert scorecard.held_text(1, 2, "small") == "**1/2 claims hold at scale `small`**"
    assert "no verdict" in scorecard.held_text(1, 2, "tiny") and "1/2" not in (
        scorecard.held_text(1, 2, "tiny")
    )
