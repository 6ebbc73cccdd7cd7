"""The golden battery (``tests/_golden.py``): every output of every step of the golden scenarios
equals the committed digests bit for bit. A change that moves a bit fails here until the digests
are regenerated on purpose (``python -m tests.regenerate_golden``)."""

from __future__ import annotations

import pytest

from . import _golden as g

GOLDEN = g.read_golden()


def _params():
    for s, v in g.CASES:
        marks = [] if (s, v) in g.FAST else [pytest.mark.slow]
        yield pytest.param(s, v, id=g.case_id(s, v), marks=marks)


@pytest.mark.parametrize("scenario, variant", list(_params()))
def test_golden_outputs_unchanged(scenario, variant):
    cid = g.case_id(scenario, variant)
    if scenario in g.NEEDS_SHARED and not g.shared_available():
        pytest.skip(f"../shared/data not found beside the repo (looked for {g.SHARED_DATA}); {cid} needs it")
    want = {k: d for k, d in GOLDEN.items() if k.rsplit("/", 1)[0] == cid}
    assert want, f"no digests for {cid} in {g.GOLDEN_FILE}: python -m tests.regenerate_golden {cid}"
    got = dict(g.run_case(scenario, variant))
    assert sorted(got) == sorted(want), f"{cid}: steps {sorted(got)} != golden {sorted(want)}"
    moved = [f"{k}.{name}" for k in want for name, a, b in zip(g.fields_of(k), want[k], got[k]) if a != b]
    assert not moved, (f"{cid}: {len(moved)} outputs moved, e.g. {moved[:12]}; if the change is meant to move "
                       f"them: python -m tests.regenerate_golden {cid}")


def test_every_case_has_digests():
    ids = {g.case_id(s, v) for s, v in g.CASES}
    have = {k.rsplit("/", 1)[0] for k in GOLDEN}
    assert ids <= have, f"cases without digests: {sorted(ids - have)}"
    assert have <= ids, f"digests of unknown cases: {sorted(have - ids)}"


def test_a_moved_bit_is_seen():
    """The digest sees one flipped bit in any field (the battery's own check)."""
    import torch

    x = torch.arange(12, dtype=torch.float32).reshape(3, 4)
    y = x.clone()
    y.view(torch.int32)[1, 2] ^= 1
    assert g.digest(x) != g.digest(y)
    assert g.digest(x) != g.digest(x.double()) and g.digest(x) != g.digest(x.reshape(4, 3))
