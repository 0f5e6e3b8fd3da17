"""Write the fixed validation split `models/splits/val.txt`: every 12th `<subset>/<name>` of the sorted list
of all samples under faces68/train (index 0, 12, 24, ...).

    python3 models/dan/split.py --data ../shared/data/faces68/train

Subsets sort as afw < helen < lfpw, so adding `lfpw/` after the first split left its 101 AFW/HELEN names
unchanged and added 67 LFPW names (168 in all). `--check` verifies the committed file instead of writing it.
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import geometry as g  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
SPLIT_FILE = os.path.join(REPO, "models", "splits", "val.txt")
HEADER = (
    "# Fixed validation split: every 12th sample of the sorted list of `<subset>/<name>` under faces68/train.\n"
    "# Never trained on by DAN or KRFWS. Regenerate: python3 models/dan/split.py (same rule).\n"
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.join(os.environ.get("HOLOFACE_DATA", os.path.join(REPO, "..", "shared", "data")), "faces68", "train"))
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args()
    names = g.list_samples(args.data)[::12]
    text = HEADER + "".join(n + "\n" for n in names)
    if args.check:
        with open(SPLIT_FILE, encoding="utf-8") as f:
            if f.read() != text:
                raise SystemExit(f"{SPLIT_FILE} does not follow the rule on {args.data}")
        print(f"{SPLIT_FILE}: {len(names)} names, follows the rule")
        return
    with open(SPLIT_FILE, "w", encoding="utf-8") as f:
        f.write(text)
    print(f"wrote {SPLIT_FILE}: {len(names)} names")


if __name__ == "__main__":
    main()
