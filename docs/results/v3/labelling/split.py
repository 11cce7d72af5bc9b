"""python split.py SHEETS KEY OUT: a batch's blind sheets into the raters' folders OUT/p{1,2}_g{1..4}.

Two passes (p1, p2) of four labellers each; labeller g of either pass gets the sheets of the
captions caps[g-1::4] (sorted), with RULE.md, PROTOCOL.md (beside this file) and numbers.txt (the
numbers on its sheets), and nothing else: no key, no run folder, no metric, no other labels.
"""

import json
import re
import shutil
import sys
from pathlib import Path

here = Path(__file__).resolve().parent
sheets, key_path, out = map(Path, sys.argv[1:4])
key = json.loads(key_path.read_text())
caps = sorted({r["caption"] for r in key.values()})
for p in (1, 2):
    for i in range(4):
        d = out / f"p{p}_g{i + 1}"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        mine = caps[i::4]
        for c in mine:
            name = re.compile(rf"sheet_{re.escape(c.replace(' ', '_'))}_\d+\.\w+")  # not a longer caption's
            for s in sheets.iterdir():
                if name.fullmatch(s.name):
                    shutil.copy(s, d / s.name)
        nums = sorted(int(n) for n, r in key.items() if r["caption"] in mine)
        (d / "numbers.txt").write_text("\n".join(map(str, nums)) + "\n")
        for f in ("RULE.md", "PROTOCOL.md"):
            shutil.copy(here / f, d / f)
        print(d.name, len(mine), "captions", len(nums), "results")
