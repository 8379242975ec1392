"""Refusals of the evaluation tools (tracker issue 55): bench_solver.py refuses unknown variants
and repeats before any work."""

import pytest

import bench_solver


# -------------------------------------------------------------------- bench_solver.py (item 14)


@pytest.mark.parametrize("arguments, named", [
    (["--variants", "eager,compile"], "'compile'"),
    (["--variants", "eager-turnd"], "'eager-turnd'"),
    (["--variants", "compiled-warm10-warm5"], "'compiled-warm10-warm5'"),
    (["--repeats", "0"], "`repeats` must be an int >= 1; got 0"),
    (["--devices", "gpu"], "`devices` must be 'cpu' and/or 'cuda'"),
])
def test_bench_solver_refuses_unknown_variants_and_repeats_before_any_work(tmp_path, monkeypatch, capsys, arguments, named):
    def no_work(*args, **kwargs):
        raise AssertionError("the benchmark ran")

    monkeypatch.setattr(bench_solver, "run", no_work)
    with pytest.raises(SystemExit) as exited:
        bench_solver.main(["--devices", "cpu", *arguments, "--out", str(tmp_path)])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert named in err
    if "--variants" in arguments:
        assert "expected 'eager' or 'compiled', then optionally each at most once '-turned', '-warmK'" in err
    assert not any(tmp_path.iterdir())


def test_bench_spec_takes_known_variants_and_refuses_others():
    spec = bench_solver.SolverBenchmark(variants=("eager", "compiled-turned-warm10-exit10.30"))
    assert spec.variants[1] == "compiled-turned-warm10-exit10.30"
    for variants in (("compile",), ("eager", "eager"), ()):
        with pytest.raises(ValueError, match="variant"):
            bench_solver.SolverBenchmark(variants=variants)
