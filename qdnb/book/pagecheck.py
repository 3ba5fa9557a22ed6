"""Checks of the rendered book, as a reader meets it.

``static_problems`` reads the HTML files (no browser): raw LaTeX left in a cell's
output, a pandas table with its 0, 1, 2... index or cells cut to "..." or styled by pandas
(``DataFrame.style``, which bypasses the book's tables), a progress bar,
and in the article's text (outside code and math) a snake_case identifier, a "± 0.0"
spread or a figure flagged degenerate (``qdnb.plotting.degeneracies``) without a note.
The book build refuses a page with any of them.

``browser_problems`` opens every page in headless Chromium (Selenium, Debian's
``chromium`` and ``chromium-driver``) and reports what only a browser sees: a
JavaScript error, a broken image, a table or figure wider than the content column (a
table scrolling inside its box counts, unless it is marked a data dump, ``.qdnb-dump``;
so does any other output scrolling sideways),
``$`` math that MathJax left unrendered, a progress-bar line in the page's text.
"""

from __future__ import annotations

import html as html_lib
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

# a progress bar as tqdm draws it, "40%|████      | 2/5 [00:01<00:02, 1.2it/s]", or with no
# bar, "40%| 2/5" (the runner drops the same lines from the pages it tidies)
PROGRESS_BAR = re.compile(r"\d+%\|.*\d+/\d+|\|\s*\d+/\d+\s*\[")
# inline math that no renderer took: "$10^6$", "$A^0$" (a price like "$5" is not math)
RAW_MATH = re.compile(r"(?<![\\$\w])\$(?!\s)[^$\n<>]{1,80}?[\^_\\{}][^$\n<>]{0,80}?(?<!\s)\$(?!\w)")
_TAG = re.compile(r"<[^>]+>")


class _Outputs(HTMLParser):
    """The cells' outputs of a page: for each ``div.cell_output``, its text (math that
    MyST rendered left out) and its tables' HTML."""

    VOID = {"br", "img", "hr", "meta", "link", "input", "col", "area", "base", "wbr", "source"}

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.outputs: list[dict[str, list[str]]] = []
        self.stack: list[tuple[str, bool, bool]] = []  # (tag, opens an output, opens math)
        self.depth = self.math = 0
        self.table: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag in self.VOID:
            return
        classes = (dict(attrs).get("class") or "").split()
        opens_output = tag == "div" and "cell_output" in classes and not self.depth
        opens_math = self.depth > 0 and "math" in classes
        self.stack.append((tag, opens_output, opens_math))
        if opens_output:
            self.outputs.append({"text": [], "tables": []})
            self.depth = 1
        elif self.depth:
            self.depth += 1
        self.math += opens_math
        if self.depth and tag == "table":
            self.table = []
        if self.table is not None:
            self.table.append(self.get_starttag_text() or "")

    def handle_endtag(self, tag):
        # a stray closing tag closes nothing (as in ``_ReaderText``)
        if tag in self.VOID or all(open_tag != tag for open_tag, _, _ in self.stack):
            return
        while self.stack:
            open_tag, opened_output, opened_math = self.stack.pop()
            if self.depth:
                self.depth -= 1
            self.math -= opened_math
            if opened_output:
                self.depth = 0
            if open_tag == tag:
                break
        if self.table is not None:
            self.table.append(f"</{tag}>")
            if tag == "table":
                self.outputs[-1]["tables"].append("".join(self.table))
                self.table = None

    def handle_data(self, data):
        if self.depth and not self.math:
            self.outputs[-1]["text"].append(data)
        if self.table is not None:
            self.table.append(html_lib.escape(data))


# an identifier a reader must not meet in the text (it goes in code type: ``num_seeds``)
SNAKE_CASE = re.compile(r"(?<![\w/.-])[a-z][a-z0-9]*(?:_[a-z0-9]+)+\b")
# a zero spread printed with decimals, as one seed gives it: "± 0.0" (the thesis's own
# "± 0" stays: it is the thesis's number)
ZERO_SPREAD = re.compile(r"±\s*0\.0+(?![\d.])")
# a number as a program prints it, not as the book writes it (``number_text``): "5.25e+05",
# "1e6"; and a grid's size with a letter x ("32x32": the book writes 32×32)
E_NOTATION = re.compile(r"(?<![\w.·-])-?\d+(?:\.\d+)?[eE][+-]?\d+(?![\w.])")
LETTER_X = re.compile(r"(?<![\w.-])\d+x\d+(?![\w.])")


class _ReaderText(HTMLParser):
    """The text of a page's article as a reader reads it: not its code (``code``,
    ``pre``, a cell's input), its math, or the navigation around it."""

    VOID = _Outputs.VOID
    SKIP_TAGS = {"code", "pre", "kbd", "samp", "script", "style", "math", "nav"}
    SKIP_CLASSES = {"math", "highlight", "cell_input", "headerlink", "toggle-details"}

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack: list[tuple[str, bool, bool]] = []  # (tag, opens the article, skips)
        self.article = self.skipped = 0
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag in self.VOID:
            return
        classes = set((dict(attrs).get("class") or "").split())
        opens = tag == "article" and "bd-article" in classes
        skips = tag in self.SKIP_TAGS or bool(classes & self.SKIP_CLASSES)
        self.stack.append((tag, opens, skips))
        self.article += opens
        self.skipped += skips

    def handle_endtag(self, tag):
        # a stray closing tag closes nothing (the elements it skips were left unclosed)
        if tag in self.VOID or all(open_tag != tag for open_tag, _, _ in self.stack):
            return
        while self.stack:
            open_tag, opened, skipped = self.stack.pop()
            self.article -= opened
            self.skipped -= skipped
            if open_tag == tag:
                break

    def handle_data(self, data):
        if self.article and not self.skipped:
            self.text.append(data)


def reader_text(page_html: str) -> str:
    """What ``_ReaderText`` keeps of a page, lines as the page breaks them."""
    parser = _ReaderText()
    parser.feed(page_html)
    return " ".join(parser.text)


def pages(html_dir: Path) -> list[Path]:
    """The book's pages (not the search, index and static files)."""
    return sorted(
        p
        for p in html_dir.rglob("*.html")
        if "_static" not in p.parts
        and "_sources" not in p.parts
        and p.name not in {"genindex.html", "search.html"}
    )


def _text(fragment: str) -> str:
    return html_lib.unescape(_TAG.sub(" ", fragment))


def static_problems(html_dir: Path) -> list[str]:
    """What a reader must not see in a cell's output, found in the HTML files."""
    from qdnb.plotting import DEGENERATE, UNEXPLAINED

    problems = []
    for page in pages(html_dir):
        name = page.relative_to(html_dir)
        parser = _Outputs()
        parser.feed(page.read_text(errors="ignore"))
        for output in parser.outputs:
            text = "".join(output["text"])
            for m in RAW_MATH.finditer(text):
                problems.append(f"{name}: raw LaTeX in an output: {m.group(0)!r}")
            for line in text.splitlines():
                if PROGRESS_BAR.search(line):
                    problems.append(f"{name}: a progress bar in an output: {line.strip()[:80]!r}")
            for table in output["tables"]:
                if re.match(r'<table[^>]*\bid="T_', table):
                    problems.append(
                        f"{name}: a table styled by pandas (DataFrame.style), not as a book "
                        "table: display the DataFrame itself"
                    )
                pandas = re.search(r'<table[^>]*class="[^"]*dataframe', table)
                if pandas and re.search(r"<th[^>]*>\s*0\s*</th>\s*<td", table):
                    problems.append(f"{name}: a pandas table shows its 0, 1, 2... index")
                for cell in re.findall(r"<td[^>]*>(.*?)</td>", table, re.S):
                    if _text(cell).strip().endswith("..."):
                        problems.append(f"{name}: a table cell cut to '...': {_text(cell)[:60]!r}")
        text = reader_text(page.read_text(errors="ignore"))
        for word in sorted(set(SNAKE_CASE.findall(text))):
            problems.append(f"{name}: an identifier in the text, not in code type: {word!r}")
        unexplained = re.escape(DEGENERATE) + r"(.{0,2000}?)" + re.escape(f"({UNEXPLAINED})")
        for m in re.finditer(unexplained, text):
            problems.append(
                f"{name}: a degenerate figure without a note saying why: {m.group(1).strip()!r}"
            )
        for rx, what in ((E_NOTATION, "a number in e-notation"), (LETTER_X, "a size as NxN")):
            for m in rx.finditer(text):
                context = text[max(0, m.start() - 40) : m.end()].split("  ")[-1].strip()
                problems.append(f"{name}: {what}, not as the book writes it: {context!r}")
        for m in ZERO_SPREAD.finditer(text):
            context = text[max(0, m.start() - 40) : m.end()].split("  ")[-1].strip()
            problems.append(f"{name}: a zero spread (one seed?): {context!r}")
    return problems


def browser_available() -> str | None:
    """Why the browser checks cannot run here, or ``None`` when they can."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (it is in requirements.lock)"
    if not (shutil.which("chromium") and shutil.which("chromedriver")):
        return (
            "Chromium and its driver are not installed (apt-get install chromium chromium-driver)"
        )
    return None


# Run in each page once MathJax has typeset it: the page's problems as strings.
_IN_PAGE = r"""
const out = [];
// what a reader can unfold is checked unfolded (the toggles' and <details>' contents)
document.querySelectorAll('.toggle-hidden').forEach(e => e.classList.remove('toggle-hidden'));
document.querySelectorAll('details').forEach(d => { d.open = true; });
const column = document.querySelector('article.bd-article') || document.querySelector('main');
const width = column ? column.getBoundingClientRect().width : window.innerWidth;
for (const img of document.images) {
  if (!img.complete || img.naturalWidth === 0) {
    out.push('a broken image: ' + img.getAttribute('src'));
  }
}
for (const el of document.querySelectorAll('figure, img, table, div.cell_output')) {
  if (el.closest('.qdnb-table, .table-wrapper, .pst-scrollable-table-container')) continue;
  if (el.closest('nav, header, footer, .bd-sidebar-primary, .bd-sidebar-secondary')) continue;
  const w = el.getBoundingClientRect().width;
  if (w > width + 2) {
    const what = el.tagName.toLowerCase() + ' ' + (el.className || '');
    out.push(`wider than the column (${Math.round(w)} > ${Math.round(width)} px): ${what}`);
  }
}
for (const wrapper of document.querySelectorAll('.qdnb-table, .pst-scrollable-table-container')) {
  if (wrapper.classList.contains('qdnb-dump')) continue;
  // wider than the column, or scrolling sideways inside its box
  const w = wrapper.getBoundingClientRect().width;
  if (w > width + 2 || wrapper.scrollWidth > wrapper.clientWidth + 2) {
    const head = [...wrapper.querySelectorAll('th')].slice(0, 3).map(th => th.innerText.trim());
    out.push(`a table wider than the column (${wrapper.scrollWidth} > ` +
             `${Math.min(wrapper.clientWidth, Math.round(width))} px): ` +
             head.join(' | ').slice(0, 80));
  }
}
// an output whose content runs past the cell scrolls sideways inside its box (a book
// table is checked above, with its data-dump exception)
for (const o of document.querySelectorAll('div.cell_output, div.cell_output div.output')) {
  if (!o.querySelector('.qdnb-table') && o.scrollWidth > o.clientWidth + 2) {
    out.push(`an output wider than the column (${o.scrollWidth} > ${o.clientWidth} px): ` +
             (o.innerText || '').trim().slice(0, 60));
  }
}
for (const o of document.querySelectorAll('div.cell_output')) {
  const text = o.innerText || '';
  if (/\d+%\|.*\|\s*\d+\/\d+/.test(text)) out.push('a progress bar in an output');
  const raw = text.match(/(^|[^\\$\w])\$(?!\s)[^$\n]{1,80}?[\^_\\{}][^$\n]{0,80}?\$(?!\w)/);
  if (raw) out.push('unrendered math in an output: ' + raw[0].trim().slice(0, 60));
}
return out;
"""


# MathJax typesets after the load event: the page is checked once it has (at most 20 s)
_WAIT_FOR_MATHJAX = """
const done = arguments[arguments.length - 1];
const t0 = Date.now();
(function wait() {
  const mj = window.MathJax;
  if (mj && mj.startup && mj.startup.promise) {
    mj.startup.promise.then(() => done());
  } else if (Date.now() - t0 > 20000 || !document.querySelector('script[src*="mathjax"]')) {
    done();
  } else {
    setTimeout(wait, 100);
  }
})();
"""


# Run in each page after ``_IN_PAGE``: every request the page made stayed on the machine
# (files and data: URIs: the book reads offline), and every video loads, fits the column,
# plays (its time advances) and is not blank (its first, middle and last frames are not all
# the same).  Returns the problems found.
_MEDIA = r"""
const done = arguments[arguments.length - 1];
const out = [];
for (const e of performance.getEntriesByType('resource')) {
  if (!/^(file|data|blob):/.test(e.name)) {
    out.push('a request leaves the machine: ' + e.name.slice(0, 80));
  }
}
const column = document.querySelector('article.bd-article') || document.querySelector('main');
const width = column ? column.getBoundingClientRect().width : window.innerWidth;
function pixels(v) {
  const c = document.createElement('canvas');
  c.width = 48; c.height = 48;
  const g = c.getContext('2d');
  g.drawImage(v, 0, 0, 48, 48);
  return g.getImageData(0, 0, 48, 48).data;
}
function differ(a, b) {
  let s = 0;
  for (let i = 0; i < a.length; i++) s += Math.abs(a[i] - b[i]);
  return s / a.length > 0.05;
}
function until(v, event) {
  return new Promise((ok, ko) => {
    v.addEventListener(event, ok, {once: true});
    v.addEventListener('error', () => ko('media error ' + (v.error && v.error.code)), {once: true});
    setTimeout(() => ko('no ' + event + ' in 10 s'), 10000);
  });
}
(async () => {
  const videos = [...document.querySelectorAll('video')];
  for (const [i, v] of videos.entries()) {
    const what = `video ${i + 1} (${(v.getAttribute('aria-label') || '').slice(0, 50)})`;
    if (v.getBoundingClientRect().width > width + 2) out.push(`${what} is wider than the column`);
    try {
      if (v.readyState < 2) await until(v, 'loadeddata');
      const frames = [];
      for (const at of [0, 0.5, 0.95]) {
        v.currentTime = at * v.duration;
        await until(v, 'seeked');
        frames.push(pixels(v));
      }
      if (!differ(frames[0], frames[1]) && !differ(frames[0], frames[2])) {
        out.push(`${what} is blank: its first, middle and last frames are the same`);
      }
      v.currentTime = 0;
      await until(v, 'seeked');
      await v.play();
      await new Promise(r => setTimeout(r, 600));
      v.pause();
      if (!(v.currentTime > 0)) out.push(`${what} does not play (its time stays at 0)`);
    } catch (e) {
      out.push(`${what} does not load: ${e}`);
    }
  }
  done(out);
})();
"""


def browser_problems(html_dir: Path, width: int = 1280) -> list[str]:
    """Open every page of ``html_dir`` in headless Chromium at ``width`` px and report
    its JavaScript errors, broken images, over-wide tables and figures, raw math and
    progress bars (``_IN_PAGE``), requests that leave the machine and videos that do not
    load, play or show anything (``_MEDIA``)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"):
        options.add_argument(flag)
    options.add_argument(f"--window-size={width},1000")
    options.binary_location = shutil.which("chromium")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    problems = []
    try:
        driver.set_page_load_timeout(60)
        driver.set_script_timeout(300)  # a page's videos are played one after another
        for page in pages(html_dir):
            name = page.relative_to(html_dir)
            driver.get(page.resolve().as_uri())
            driver.execute_async_script(_WAIT_FOR_MATHJAX)
            for entry in driver.get_log("browser"):
                if entry.get("level") == "SEVERE":
                    problems.append(f"{name}: a JavaScript error: {entry.get('message', '')[:200]}")
            problems += [f"{name}: {p}" for p in driver.execute_script(_IN_PAGE)]
            problems += [f"{name}: {p}" for p in driver.execute_async_script(_MEDIA)]
    finally:
        driver.quit()
    return problems
