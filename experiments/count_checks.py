"""Count the argument-check sites outside ``validation/`` (issue 34, item 4).

A check site is a line of ``src/flowmaps_jax`` (minus ``validation/``) that calls a
``check_*(`` function (definitions included) or raises ``ValueError``: the same count as::

    grep -rn --include=*.py "check_[a-z_]*(" src/flowmaps_jax | grep -v /validation/ | wc -l
    grep -rn --include=*.py "raise ValueError" src/flowmaps_jax | grep -v /validation/ | wc -l

Prints one row per area (and with ``--files`` per module), the two kinds apart, and the total.
``--at-most N`` exits 1 when the total is over N, so a test keeps the count from creeping back::

    python experiments/count_checks.py --files
    python experiments/count_checks.py --at-most 308
"""

from __future__ import annotations

import argparse
import pathlib
import re
import sys

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "src" / "flowmaps_jax"
CHECK_CALL = re.compile(r"check_[a-z_]*\(")
RAISE = re.compile(r"raise ValueError")

# area -> module path prefixes (relative to the package); the first that matches wins
AREAS = (
    ("homes simulator", ("flowsim/homes/",)),
    ("2-D simulator", ("flowsim/",)),
    ("homes model", ("homes/",)),
    ("object search", ("search/",)),
    ("evaluation", ("evaluation/", "evaluate.py")),
    ("store and training", ("store/", "training/", "export.py", "train.py")),
    ("model side", ("",)),
)


def area_of(relative: str) -> str:
    """The area a module (path relative to the package, with ``/``) belongs to."""
    return next(name for name, prefixes in AREAS if relative.startswith(prefixes))


def count(root: pathlib.Path = PACKAGE) -> dict[str, tuple[int, int]]:
    """module path -> (lines calling ``check_*(``, lines raising ``ValueError``); no validation/."""
    counts = {}
    for path in sorted(root.rglob("*.py")):
        relative = path.relative_to(root).as_posix()
        if relative.startswith("validation/"):
            continue
        lines = path.read_text().splitlines()
        calls = sum(bool(CHECK_CALL.search(line)) for line in lines)
        raises = sum(bool(RAISE.search(line)) for line in lines)
        if calls or raises:
            counts[relative] = (calls, raises)
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--files", action="store_true", help="one row per module as well")
    parser.add_argument("--at-most", type=int, default=None, metavar="N",
                        help="exit 1 if the total is over N")
    args = parser.parse_args(argv)
    if args.at_most is not None and args.at_most < 0:
        parser.error(f"--at-most must be >= 0, got {args.at_most}")
    counts = count()
    by_area: dict[str, list[int]] = {name: [0, 0] for name, _ in AREAS}
    for relative, (calls, raises) in counts.items():
        by_area[area_of(relative)][0] += calls
        by_area[area_of(relative)][1] += raises
    print("| area | check_*( | raise ValueError | sites |")
    print("|---|---|---|---|")
    for name, (calls, raises) in by_area.items():
        print(f"| {name} | {calls} | {raises} | {calls + raises} |")
    calls = sum(c for c, _ in counts.values())
    raises = sum(r for _, r in counts.values())
    print(f"| **total** | {calls} | {raises} | **{calls + raises}** |")
    if args.files:
        print("\n| module | sites |\n|---|---|")
        for relative, (c, r) in sorted(counts.items(), key=lambda kv: -sum(kv[1])):
            print(f"| {relative} | {c + r} |")
    if args.at_most is not None and calls + raises > args.at_most:
        print(f"{calls + raises} check sites, over --at-most {args.at_most}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
