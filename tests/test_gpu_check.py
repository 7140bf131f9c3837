"""vkgrl_newton.tools.gpu_check on the CPU with small sizes: the report it writes and the inputs it refuses
(on a CUDA machine the same command runs the full sizes)."""

import json

import pytest


@pytest.mark.slow
def test_cpu_report(wp_cpu, tmp_path):
    from vkgrl_newton.tools import gpu_check

    out = tmp_path / "r.json"
    rc = gpu_check.main(["--device", "cpu", "--worlds", "2", "--steps", "2", "--tasks", "PegInsert",
                         "--checks", "graph_vs_eager", "sac_updates", "kernel_bench", "--out", str(out)])
    report = json.loads(out.read_text())
    assert rc == 0, report.get("failures")
    assert report["complete"] and report["failures"] == []
    assert report["meta"]["device"] == "cpu" and report["meta"]["device_name"]
    checks = report["checks"]
    assert set(checks) == {"graph_vs_eager", "sac_updates", "kernel_bench"}  # parts_mesh not requested
    assert all(c["wall_s"] > 0 for c in checks.values())

    entry = checks["graph_vs_eager"]["results"]["PegInsert"]["2"]
    assert entry["bitwise_equal"] is True and entry["compared_steps"] == 4  # 2 warm-up + 2 steps
    assert entry["compared_delta_steps"] == 3  # and the SAC path's 3 delta-action steps
    assert entry["max_abs_diff"] == {"body_q": 0.0, "obs": 0.0}
    for mode in ("eager", "graph"):
        assert entry[mode]["env_steps_per_s"] > 0 and entry[mode]["ms_per_env_step"] > 0
        assert entry[mode]["timed_steps"] == 2
    assert entry["eager"]["captures"] == 0 and entry["graph"]["captures"] >= 1

    assert checks["sac_updates"]["grad_steps_per_s"] > 0 and checks["sac_updates"]["updates"] == 20
    rows = checks["kernel_bench"]["rows"]
    assert rows and {r["kernel"] for r in rows} == {"kmp_horizon"} and all(r["device"] == "cpu" for r in rows)


def test_parts_skipped_on_cpu_and_bad_inputs_refused(wp_cpu, tmp_path, capsys):
    from vkgrl_newton.tools import gpu_check

    # an existing report is never overwritten
    out = tmp_path / "old.json"
    out.write_text("keep me")
    with pytest.raises(SystemExit):
        gpu_check.main(["--device", "cpu", "--checks", "sac_updates", "--out", str(out)])
    assert out.read_text() == "keep me"
    assert str(out) in capsys.readouterr().err

    # an unknown check: the error names the allowed ones
    with pytest.raises(SystemExit):
        gpu_check.main(["--device", "cpu", "--checks", "nope", "--out", str(tmp_path / "a.json")])
    err = capsys.readouterr().err
    assert "--checks" in err and all(name in err for name in gpu_check.CHECKS)

    for bad in (["--worlds", "0"], ["--steps", "500"], ["--budget-s", "-1"], ["--device", "cuda:7"]):
        with pytest.raises(SystemExit):
            gpu_check.main(["--device", "cpu", *bad, "--out", str(tmp_path / "b.json")])
        assert bad[0] in capsys.readouterr().err
    assert not (tmp_path / "a.json").exists() and not (tmp_path / "b.json").exists()

    # parts_mesh on a CPU without --cpu-parts: recorded as skipped, costs nothing
    rc = gpu_check.main(["--device", "cpu", "--checks", "parts_mesh", "--out", str(tmp_path / "p.json")])
    report = json.loads((tmp_path / "p.json").read_text())
    assert rc == 0 and report["checks"] == {"parts_mesh": {"skipped": "cpu: mesh SDF needs CUDA"}}


def test_old_module_path_forwards_to_the_tool():
    """`python -m vkgrl_newton.gpu_check` and `from vkgrl_newton import gpu_check` still reach the tool."""
    from vkgrl_newton import gpu_check as old
    from vkgrl_newton.tools import gpu_check

    assert old.main is gpu_check.main and old.cli is gpu_check.cli and old.CHECKS == gpu_check.CHECKS
