"""Sphinx additions of the book (loaded through ``_config.yml``'s ``local_extensions``).

- The bibliography is labelled as the text cites it, author and year ("Lehman and
  Stanley, 2011"), not numbered: the ``authoryear`` pybtex style.
- An inline script registered twice (sphinx-thebe's configuration, whose second copy
  throws "THEBE_JS_URL has already been declared" on every page) is emitted once.
"""

from __future__ import annotations

from pybtex.plugin import register_plugin
from pybtex.style.formatting.plain import Style as PlainStyle
from pybtex.style.labels import BaseLabelStyle


def _surname(person) -> str:
    return " ".join(person.prelast_names + person.last_names) or "Anon."


class AuthorYearLabels(BaseLabelStyle):
    """ "Surname, year", "Surname and Other, year" or "Surname et al., year"; a letter
    tells apart two entries that would share a label."""

    def format_labels(self, sorted_entries):
        labels = [self._label(entry) for entry in sorted_entries]
        seen: dict[str, int] = {}
        for label in labels:
            seen[label] = seen.get(label, 0) + 1
        suffix: dict[str, int] = {}
        for label in labels:
            if seen[label] == 1:
                yield label
            else:
                suffix[label] = suffix.get(label, 0) + 1
                yield f"{label}{'abcdefghij'[suffix[label] - 1]}"

    @staticmethod
    def _label(entry) -> str:
        people = entry.persons.get("author") or entry.persons.get("editor") or []
        year = entry.fields.get("year", "n.d.")
        if not people:
            return f"{entry.fields.get('title', entry.key)[:24]}, {year}"
        if len(people) == 1:
            names = _surname(people[0])
        elif len(people) == 2:
            names = f"{_surname(people[0])} and {_surname(people[1])}"
        else:
            names = f"{_surname(people[0])} et al."
        return f"{names}, {year}"


class AuthorYearStyle(PlainStyle):
    default_label_style = "authoryear"
    default_sorting_style = "author_year_title"


register_plugin("pybtex.style.labels", "authoryear", AuthorYearLabels)
register_plugin("pybtex.style.formatting", "authoryear", AuthorYearStyle)


def _one_copy_of_each_script(app, pagename, templatename, context, doctree) -> None:
    scripts = context.get("script_files")
    if not scripts:
        return
    seen, kept = set(), []
    for script in scripts:
        # an inline script registered once with no file name (None) and once with an
        # empty one ("") is one script
        attributes = getattr(script, "attributes", {})
        key = (getattr(script, "filename", None) or "", tuple(sorted(attributes.items())))
        if key not in seen:
            seen.add(key)
            kept.append(script)
    scripts[:] = kept


def setup(app):
    app.connect("html-page-context", _one_copy_of_each_script, priority=900)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
