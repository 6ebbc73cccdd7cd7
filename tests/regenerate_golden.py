"""Regenerate the golden battery's digests (``tests/data/golden.txt``) on purpose.

    .venv/bin/python -m tests.regenerate_golden            # every case (~2 min on 2 cores)
    .venv/bin/python -m tests.regenerate_golden mono/lo    # only these cases (the rest is kept)

Run it only for a change that is meant to move outputs, after checking why they move, and commit
the new file with the change, so that its diff shows which outputs moved. Cases that need
``../shared/data`` are kept as they are when it is absent.
"""

from __future__ import annotations

import argparse
import sys

import torch

from . import _golden as g


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="*", help="scenario/variant ids (default: all)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    known = {g.case_id(s, v): (s, v) for s, v in g.CASES}
    bad = [c for c in args.cases if c not in known]
    if bad:
        print(f"unknown case(s) {bad}; known: {sorted(known)}", file=sys.stderr)
        return 2
    old = g.read_golden() if g.GOLDEN_FILE.exists() else {}
    new = dict(old)
    for s, v in ([known[c] for c in args.cases] if args.cases else g.CASES):
        cid = g.case_id(s, v)
        if s in g.NEEDS_SHARED and not g.shared_available():
            print(f"{cid}: ../shared/data absent, kept as it was")
            continue
        for k in [k for k in new if k.rsplit("/", 1)[0] == cid]:
            del new[k]
        got = dict(g.run_case(s, v))
        new.update(got)
        moved = sum(old.get(k) != d for k, d in got.items())
        print(f"{cid}: {len(got)} lines, {moved} changed")
    g.write_golden(new)
    print(f"wrote {g.GOLDEN_FILE} ({len(new)} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
