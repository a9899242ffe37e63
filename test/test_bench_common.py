"""The benchmarks' shared result writer: lean files unless the per-step detail is asked for."""

import json

from soft_tissue_sim.bench.common import columns, parser, publish


def test_result_files_hold_the_detail_only_when_asked(tmp_path):
    rows = [{"step": k, "wall_ms": 1.0 / 3.0 + k, "iterations": 4} for k in range(500)]
    figures = {"summary": {"steps": 500}, "plot": {"steps": columns(rows, ("step", "wall_ms"))}}
    drawn = []
    for detail in (False, True):
        args = parser("test", None).parse_args(["--out", str(tmp_path / str(detail))] + (["--detail"] if detail else []))
        path = publish("test", "cpu", figures, args, lambda f, prefix: drawn.append((f["device"], prefix)),
                       detail={"steps_detail": rows})
        doc = json.load(open(path))
        assert doc["benchmark"] == "test" and doc["warp_device"] == "cpu" and path.name == "test_cpu.json"
        assert doc["figures"]["summary"] == {"steps": 500}
        assert ("steps_detail" in doc["figures"]) == detail
        if detail:
            assert doc["figures"]["steps_detail"] == rows
    lean, full = (tmp_path / "False" / "test_cpu.json").stat().st_size, (tmp_path / "True" / "test_cpu.json").stat().st_size
    assert lean < full / 2
    assert len(drawn) == 2 and drawn[0][0].startswith("CPU") and drawn[0][1].endswith("test_cpu")
    plotted = json.load(open(tmp_path / "False" / "test_cpu.json"))["figures"]["plot"]["steps"]
    assert plotted["step"] == list(range(500)) and plotted["wall_ms"][0] == 0.33333  # 5 significant digits



def test_the_commit_can_be_named_for_a_copy_without_its_own_git(monkeypatch):
    from soft_tissue_sim.bench.common import git_commit

    monkeypatch.setenv("STS_COMMIT", "abc1234")
    assert git_commit() == "abc1234"
    monkeypatch.delenv("STS_COMMIT")
    assert git_commit() != "abc1234"
