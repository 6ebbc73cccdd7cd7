"""``benchmarks/roofline_report.py``: the modelled-figures report from roofline.py's JSON (synthetic
figures here: the tool itself lives in ../shared and is not needed), and ``benchmarks/gpu.sh`` runs it."""

from __future__ import annotations

import importlib.util
import json

from tests.conftest import REPO


def _report():
    spec = importlib.util.spec_from_file_location("roofline_report", REPO / "benchmarks" / "roofline_report.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _fig(B, kernels, mb_per_stream, graph_s):
    tot = dict(kernels=kernels, read=mb_per_stream * 1e6 * B / 2, write=mb_per_stream * 1e6 * B / 2,
               peak_live_bytes=2 ** 30 * B / 16)
    for d in ("H100", "H200"):
        tot.update({f"{d}:graph": graph_s, f"{d}:eager": 2 * graph_s})
    row = dict(calls=kernels, read=tot["read"], write=tot["write"], **{"H100:graph": graph_s})
    return dict(B=B, totals=tot, rows={"lk": row},
                biggest_tensor=[1e6, ["lk", "index", "lk/capturable.py:1 f", [B, 3], "float32"]])


def _write(path, figs):
    path.write_text(json.dumps({"results": {str(f["B"]): f for f in figs}}))
    return str(path)


def test_render_before_after(tmp_path):
    mod = _report()
    before = _write(tmp_path / "b.json", [_fig(1, 4415, 1879.0, 0.01128), _fig(16, 4415, 1872.0, 0.01969)])
    after = _write(tmp_path / "a.json", [_fig(1, 2000, 100.0, 0.005), _fig(16, 2000, 90.0, 0.004)])
    out = tmp_path / "roofline.md"
    assert mod.main(["render", "--before", before, "--after", after, "--out", str(out)]) == 0
    text = out.read_text()
    assert "| 1 | 4,415 → 2,000 | 1.88 → 0.10 | 1,879 → 100 | 11.28 → 5.00 |" in text
    assert "| 16 | 4,415 → 2,000 |" in text and "0.25 → 0.250" not in text
    assert "| lk | 4,415 → 2,000 | 1,872.0 → 90.0 |" in text
    assert "Modelled, not measured" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json", "roofline.md"]  # no temp left


def test_beside_measured(tmp_path):
    mod = _report()
    model = _write(tmp_path / "m.json", [_fig(16, 2000, 90.0, 0.004)])
    measured = tmp_path / "p.json"
    measured.write_text(json.dumps({"machine": "H100", "rows": [
        {"B": 16, "device": "cuda", "compiled": True, "torch_ms_per_step": 7.5},
        {"B": 16, "device": "cpu", "torch_ms_per_step": 100.0}]}))
    out = tmp_path / "beside.md"
    assert mod.main(["beside", "--measured", str(measured), "--modelled", model, "--out", str(out)]) == 0
    rows = [ln for ln in out.read_text().splitlines() if ln.startswith("| 16 ")]
    assert rows == ["| 16 | yes | 7.50 | 8.00 | 4.00 | 8.00 | 4.00 |"]


def test_missing_tool_is_a_clear_error(tmp_path, capsys):
    mod = _report()
    assert mod.main(["run", "--tool", str(tmp_path / "nope.py"), "--out", str(tmp_path / "x.json")]) == 2
    assert "nope.py not found" in capsys.readouterr().err


def test_gpu_script_runs_the_model():
    text = (REPO / "benchmarks" / "gpu.sh").read_text()
    assert "roofline_report.py run" in text and "roofline_report.py beside" in text


_FAKE_SIMCUDA = '''
import weakref

class T:
    pass

def _handle(x):
    orig = {id(x): x}

    def wrap(y):
        if isinstance(y, list):
            return [wrap(v) for v in y]  # calls itself: a reference cycle holding orig
        return orig.get(id(y), y)

    out = x
    return wrap(out)
'''


def _fake_tool(tmp_path, handle_src):
    (tmp_path / "simcuda.py").write_text(handle_src)
    (tmp_path / "roofline.py").write_text(
        "import gc, sys, weakref\nimport simcuda\n\n"
        "def main(argv):\n"
        "    gc.disable()\n"
        "    t = simcuda.T()\n"
        "    simcuda._handle(t)\n"
        "    r = weakref.ref(t)\n"
        "    del t\n"
        "    print('freed' if r() is None else 'alive', argv)\n"
        "    return 0\n")
    return str(tmp_path / "roofline.py")


def test_tool_frees_inplace_inputs_at_their_last_reference(tmp_path, capsys, monkeypatch):
    """``_tool`` rewrites simcuda's ``return wrap(out)`` so that an op's inputs do not outlive it
    in the wrapper's reference cycle (the tool's peak memory); here a stand-in tool shows it."""
    mod = _report()
    tool = _fake_tool(tmp_path, _FAKE_SIMCUDA)
    monkeypatch.setattr("sys.path", list(__import__("sys").path))
    monkeypatch.delitem(__import__("sys").modules, "simcuda", raising=False)
    monkeypatch.delitem(__import__("sys").modules, "roofline", raising=False)
    assert mod.main(["_tool", tool, "--B", "1"]) == 0
    assert "freed ['--B', '1']" in capsys.readouterr().out


def test_tool_refuses_a_changed_simcuda(tmp_path, capsys, monkeypatch):
    mod = _report()
    tool = _fake_tool(tmp_path, _FAKE_SIMCUDA.replace("return wrap(out)", "return wrap(x)"))
    monkeypatch.setattr("sys.path", list(__import__("sys").path))
    monkeypatch.delitem(__import__("sys").modules, "simcuda", raising=False)
    monkeypatch.delitem(__import__("sys").modules, "roofline", raising=False)
    assert mod.main(["_tool", tool]) == 2
    assert "--keep-inplace-cycle" in capsys.readouterr().err
