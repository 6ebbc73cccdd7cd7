"""What is alive at each stage's peak of device memory in the capturable mono step (modelled).

``../shared/tools/cuda_sim/roofline.py`` reports the step's peak of live device memory and the
stage where it happens. This runs its measurement (with ``roofline_report.py``'s fix of the tool's
reference cycle) and records, for every stage, the moment its live bytes were highest and which
tensors were alive then, grouped by the stage and source line that made them, per stream:

    PYTHONPATH=$PWD .venv/bin/python benchmarks/peak_live.py [--B 4] [--stages 4] [--top 14]

Tensors made before the measured steps (the tracker's state and the package's per-size constants)
show as ``(before the measured steps)``; at small B the constants weigh more per stream than at
large B (measured: ~3.2 MiB per stream at B = 4, ~0 at B = 256).
"""

from __future__ import annotations

import argparse
import collections
import inspect
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOOLS = REPO.parent / "shared" / "tools" / "cuda_sim"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--B", type=int, default=4, help="streams (default 4)")
    ap.add_argument("--stages", type=int, default=4, help="stages to list, highest peak first (default 4)")
    ap.add_argument("--top", type=int, default=14, help="tensor groups per stage (default 14)")
    args = ap.parse_args(argv)
    if not (TOOLS / "roofline.py").is_file():
        print(f"peak_live.py: {TOOLS / 'roofline.py'} not found (the shared cuda_sim tools)", file=sys.stderr)
        return 2
    sys.path.insert(0, str(TOOLS))
    sys.path.insert(0, str(REPO / "benchmarks"))
    import simcuda
    from roofline_report import _HANDLE_RETURN

    src = inspect.getsource(simcuda._handle)  # roofline_report._tool's fix: in-place inputs not kept alive
    src = src.replace(_HANDLE_RETURN, "    try:\n        return wrap(out)\n    finally:\n        orig = None\n")
    exec(compile(src, simcuda.__file__, "exec"), simcuda.__dict__)
    import roofline

    R = roofline.Recorder
    plain_track = R.track

    def track(self, ts, where=None):
        if not hasattr(self, "made"):
            self.made, self.stage_peak = {}, {}
        for t in ts:
            if isinstance(t, simcuda.SimCuda):
                try:
                    p = t.elem.untyped_storage().data_ptr()
                except Exception:
                    continue
                if p not in self.live:
                    self.made[p] = (where, tuple(t.shape), str(t.dtype).replace("torch.", ""))
        plain_track(self, ts, where)
        if where is not None and self.cur is not None and self.live_bytes > self.stage_peak.get(where[0], (0,))[0]:
            self.stage_peak[where[0]] = (self.live_bytes, where,
                                         [(e[1], self.made.get(p)) for p, e in self.live.items()])

    R.track = track
    plain_measure = roofline.measure
    B = args.B

    found = []

    def measure(*a, **k):
        out = plain_measure(*a, **k)
        found.append(out[0].stage_peak)
        return out

    roofline.measure = measure
    import io
    from contextlib import redirect_stdout

    with redirect_stdout(io.StringIO()):  # the tool's own report is not this script's
        rc = roofline.main(["--B", str(B), "--steps", "2", "--warmup", "4",
                            "--tracker-kwargs", '{"capturable": true}'])
    for _, (peak, where, items) in sorted(found[0].items(), key=lambda kv: -kv[1][0])[: args.stages]:
        print(f"\n{where[0]}: {peak / 2**20 / B:.2f} MiB per stream at {where[2]} ({where[1]})")
        size, count = collections.Counter(), collections.Counter()
        for nb, m in items:
            key = f"{m[0][0]}: {m[0][2]} {m[2]}{list(m[1])}" if m and m[0] else "(before the measured steps)"
            size[key] += nb
            count[key] += 1
        for key, nb in size.most_common(args.top):
            print(f"  {nb / 2**20 / B:7.2f} MiB  x{count[key]:<4d} {key}")
    return rc or 0


if __name__ == "__main__":
    sys.exit(main())
