"""The thesis's names for the book's environments, wherever a reader sees one: titles,
tables, legends, claims; ``markdown_words`` puts a machine-written line in a reader's
words."""

import re

ENV_LABELS = {
    "pointmaze": "Point-Maze",
    "antmaze": "Ant-Maze",
    "anttrap": "Ant-Trap",
    "ant_omni": "Ant-Omni",
    "halfcheetah_uni": "Halfcheetah-Uni",
}

# What a reader sees for the book's other internal names (a predictor, a sweep's variant)
# when a table shows one.
READER_NAMES = {
    **ENV_LABELS,
    "flt": "FLT",
    "flt_teacher_forced": "FLT, true inputs (one step)",
    "mean_frame": "mean frame",
    "copy_previous": "previous frame copied",
    "stoch": "stochastic mix",
    "stoch_fresh": "stochastic mix, fresh key",
}

# a word with an underscore is an identifier or a path (a config's field, a notebook's
# name, ``agac_torch/configs/point_maze.yaml``): a reader meets it in code type
IDENTIFIER = re.compile(r"(?<![\w/.:-])[A-Za-z0-9][\w./-]*_[\w./-]*[A-Za-z0-9]")
# an environment's internal name standing as a word of its own (not inside a path)
_ENV_WORD = re.compile(
    r"(?<![\w/.-])(" + "|".join(sorted(ENV_LABELS, key=len, reverse=True)) + r")(?![\w/.-])"
)
# what is left as written: code spans, link targets, addresses
_KEPT = re.compile(r"(`[^`]*`|\]\([^)]*\)|<?https?://\S+)")


def markdown_words(text: str) -> str:
    """``text`` (a loop's name, a reason a program wrote) as Markdown for a reader: the
    environments by their thesis names, any other identifier in code type; code spans,
    links and addresses stay as they are."""
    out = []
    for part in _KEPT.split(text):
        if _KEPT.fullmatch(part):
            out.append(part)
            continue
        part = _ENV_WORD.sub(lambda m: ENV_LABELS[m.group(1)], part)
        out.append(IDENTIFIER.sub(lambda m: f"`{m.group(0)}`", part))
    return "".join(out)
