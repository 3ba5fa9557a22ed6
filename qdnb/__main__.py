"""``python -m qdnb``: list notebooks, run them, build the book."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from qdnb.book import publish, runner
from qdnb.core import paths
from qdnb.core.config import SCALES


def add_checkpoint_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--resume",
        dest="checkpoints",
        action="store_const",
        const="resume",
        help="long loops save checkpoints and resume from this run's latest (the default)",
    )
    group.add_argument(
        "--fresh",
        dest="checkpoints",
        action="store_const",
        const="fresh",
        help="ignore (and replace) this run's checkpoints: every loop starts from scratch",
    )
    group.add_argument(
        "--no-checkpoints",
        dest="checkpoints",
        action="store_const",
        const="off",
        help="save no checkpoints",
    )
    parser.set_defaults(checkpoints="resume")
    parser.add_argument(
        "--deterministic",
        action="store_true",
        help="deterministic GPU kernels (--xla_gpu_deterministic_ops=true): slower",
    )
    parser.add_argument(
        "--devices",
        metavar="N",
        default=None,
        help="XLA host devices the notebooks' CPU runs use (QDNB_DEVICES; default: one per "
        "core; 1 runs everything on one device); GPUs and TPUs are not affected",
    )


def set_devices(value: str | None) -> None:
    """``--devices``: checked here (a clear error before any notebook starts), then
    handed to the kernels as ``QDNB_DEVICES``."""
    if value is not None:
        from qdnb.core.sharding import requested_devices

        os.environ["QDNB_DEVICES"] = str(requested_devices(value))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m qdnb", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list notebooks and scales")
    run = sub.add_parser("run", help="execute notebooks with papermill")
    run.add_argument("notebooks", nargs="+", metavar="NOTEBOOK")
    run.add_argument("--scale", default="tiny", help=f"one of {', '.join(SCALES)} (default: tiny)")
    run.add_argument("--seed", type=int, default=0)
    add_checkpoint_flags(run)
    book = sub.add_parser("book", help="execute every notebook, then build the HTML book")
    book.add_argument(
        "--scale", default="small", help=f"one of {', '.join(SCALES)} (default: small)"
    )
    book.add_argument("--seed", type=int, default=0)
    book.add_argument(
        "--force", action="store_true", help="re-execute even when an identical execution exists"
    )
    add_checkpoint_flags(book)
    pub = sub.add_parser("publish", help="pack a finished run into one archive with a manifest")
    pub.add_argument("scale")
    pub.add_argument("notebook")
    pub.add_argument("--out", default=None, help="the archive's path (default: data/published/...)")
    pub.add_argument(
        "--verdicts",
        action="store_true",
        help="publish only the run's claims and provenance (data/published/<scale>/<notebook>/"
        "verdicts.json, kilobytes, kept in the repository and shown by every build)",
    )
    imp = sub.add_parser("import", help="check a published run's archive and unpack it")
    imp.add_argument("archive")
    imp.add_argument("--replace", action="store_true", help="replace a run already here")
    dry = sub.add_parser(
        "dryrun",
        help="run each long loop's first steps at a scale's shapes; project hours and memory",
    )
    dry.add_argument("notebooks", nargs="+", metavar="NOTEBOOK", help="notebook names, or all")
    dry.add_argument(
        "--scale", default="paper", help=f"one of {', '.join(SCALES)} (default: paper)"
    )
    dry.add_argument("--seed", type=int, default=0)
    dry.add_argument(
        "--out", default=None, help="the report (default: bench/results/<scale>_dryrun.json)"
    )
    dry.add_argument(
        "--report-only",
        action="store_true",
        help="rebuild the report from the last dry run's records (new GPU rates), running nothing",
    )
    dry.add_argument(
        "--devices",
        metavar="N",
        default=None,
        help="XLA host devices of the CPU kernels (as for run)",
    )
    check = sub.add_parser(
        "check-pages", help="open every page of the built book in headless Chromium and report"
    )
    check.add_argument("html", nargs="?", default="book/_build/html", help="the built book")
    args = parser.parse_args(argv)

    try:
        if args.command == "list":
            print("notebooks:", " ".join(runner.notebook_names()))
            print("scales:   ", " ".join(SCALES))
        elif args.command == "run":
            runner.check_notebooks(args.notebooks)
            set_devices(args.devices)
            executed = runner.run_notebooks(
                args.notebooks,
                args.scale,
                args.seed,
                checkpoints=args.checkpoints,
                deterministic=args.deterministic,
            )
            for path in executed:
                print(f"executed: {path}")
        elif args.command == "book":
            set_devices(args.devices)
            index = runner.build_book(
                args.scale,
                args.seed,
                force=args.force,
                checkpoints=args.checkpoints,
                deterministic=args.deterministic,
            )
            print(f"book: {index}")
        elif args.command == "publish" and args.verdicts:
            from qdnb.book import verdicts

            print(f"published: {verdicts.publish_verdicts(args.scale, args.notebook)}")
        elif args.command == "publish":
            print(f"published: {publish.publish(args.scale, args.notebook, args.out)}")
        elif args.command == "import":
            print(f"imported: {publish.import_archive(args.archive, args.replace)}")
        elif args.command == "dryrun":
            from qdnb.book import dryrun_report as dryrun
            from qdnb.core.config import check_scale

            check_scale(args.scale)
            dryrun.resolve(args.notebooks)
            set_devices(args.devices)
            out = Path(args.out) if args.out else None
            if args.report_only:
                names = None if args.notebooks == ["all"] else args.notebooks
                report = dryrun.resummarise(args.scale, out, names=names)
            else:
                report = dryrun.dry_run(args.notebooks, args.scale, args.seed, out=out)
            print(dryrun.text_table(report))
            print(f"report: {paths.shown(out or dryrun.report_path(args.scale))}")
            ran = dryrun.resolve(args.notebooks)
            failed = [n for n in ran if report["notebooks"].get(n, {}).get("status") == "failed"]
            return 1 if failed else 0
        elif args.command == "check-pages":
            from qdnb.book import pagecheck

            html = Path(args.html)
            if not (html / "index.html").exists():
                raise ValueError(f"no built book at {html}: run `make book` first")
            why_not = pagecheck.browser_available()
            if why_not:
                raise RuntimeError(f"cannot open the pages in a browser: {why_not}")
            problems = pagecheck.static_problems(html) + pagecheck.browser_problems(html)
            for problem in problems:
                print(problem)
            print(f"{len(pagecheck.pages(html))} pages checked, {len(problems)} problem(s)")
            return 1 if problems else 0
    except (ValueError, runner.NotebookFailed, RuntimeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1 if not isinstance(err, ValueError) else 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
