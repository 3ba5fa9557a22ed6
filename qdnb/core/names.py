"""The thesis's names for the book's environments, wherever a reader sees one: titles,
tables, legends, claims; ``markdown_words`` puts a machine-written line in a reader's
words; ``number_text``, ``seeds_text`` and ``mean_sd`` write numbers, counts and means
over seeds as the book does (``over_seeds_text`` in captions); ``machine_text`` a
recorded device."""

import math
import re

import numpy as np

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
    # optimisers, as papers name them
    "adam": "Adam",
    "sgd": "SGD",
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


_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def number_text(value: float, digits: int = 2) -> str:
    """A number as the book writes it in text and tables: ``digits`` significant
    figures, thousands separators up to 99,999, powers of ten beyond (and below 10⁻⁴)
    as the thesis prints them, 1.6·10⁶ and 10⁸; ∞ for never."""
    x = float(value)
    if math.isnan(x):
        return "—"
    if math.isinf(x):
        return "∞" if x > 0 else "−∞"
    text = f"{x:.{digits}g}"
    if "e" not in text:
        whole = float(text)
        if abs(whole) >= 1000 and whole == int(whole):
            return f"{int(whole):,}"
        return text
    mantissa, exponent = text.split("e")
    e = int(exponent)
    if -4 < e < 5:  # 1.6e+04 -> 16,000, -1.3e+02 -> -130
        rounded = float(text)
        return f"{int(rounded):,}" if rounded == int(rounded) else f"{rounded:g}"
    power = f"10{str(e).translate(_SUPERSCRIPT)}"
    return power if float(mantissa) == 1 else f"{mantissa}·{power}"


_DEVICE = re.compile(r"^(\w+): (.+?) x(\d+) \((.*)\)$")


def machine_text(recorded: str) -> str:
    """A recorded ``device()`` string in a reader's words: "cpu: cpu x2 (2 CPU cores, AMD
    EPYC)" reads "2 CPU cores (AMD EPYC)", "gpu: NVIDIA H100 x1 (16 CPU cores, ...)" reads
    "1 NVIDIA H100 (beside 16 CPU cores, ...)"; any other text is returned as it is."""
    m = _DEVICE.match(recorded.strip())
    if not m:
        return recorded
    platform, kind, count, host = m.groups()
    cores, _, processor = host.partition(", ")
    if platform == "cpu":
        return f"{cores} ({processor})" if processor else cores
    return f"{count} {kind} (beside {host})"


def seeds_text(n: int, noun: str = "seed") -> str:
    """``n`` seeds, in words: "1 seed", "4 seeds" (never "seed(s)")."""
    return f"{n} {noun}" + ("" if n == 1 else "s")


def over_seeds_text(n: int, spread: str = "range shaded") -> str:
    """How a figure or table over ``n`` seeds says so: "mean over 3 seeds, range shaded";
    for one seed "one seed" (no mean, no range)."""
    return (
        "one seed" if n == 1 else f"mean over {seeds_text(n)}" + (f", {spread}" if spread else "")
    )


def majority_text(n: int) -> str:
    """How a comparison over ``n`` seeds is called: "on the mean over 3 seeds and on most
    of them", and for one seed "on its one seed" (no mean, no majority to speak of)."""
    return "on its one seed" if n == 1 else f"on the mean over {seeds_text(n)} and on most of them"


def mean_sd(values, digits: int = 1, diverged: int | None = None) -> str:
    """A mean over seeds as the book writes it: ``mean ± sd (n seeds)``; one seed is its
    value and "(1 seed)", never "± 0.0"; seeds that diverged (NaN, or ``diverged`` of
    them when given) are left out and counted."""
    v = np.asarray(values, float).ravel()
    finite = v[np.isfinite(v)]
    lost = v.size - finite.size if diverged is None else diverged
    if not finite.size:
        return "diverged" if lost else "—"
    text = f"{finite.mean():,.{digits}f}"  # thousands separated, as number_text writes them
    if finite.size > 1:
        text += f" ± {finite.std():,.{digits}f} ({finite.size} seeds)"
    else:
        text += " (1 seed)"
    return text + (f", {lost} diverged" if lost else "")
