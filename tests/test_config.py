import pytest

from mmpc import OptimizerConfig


def test_defaults_are_the_authors_numbers():
    cfg = OptimizerConfig()
    assert (cfg.horizon, cfg.num_steps, cfg.order, cfg.iterations) == (8.0, 100, 10, 100)
    assert (cfg.ellipse_a, cfg.ellipse_b, cfg.a_max) == (5.6, 3.0, 4.0)
    rho = cfg.rho_schedule()
    assert len(rho) == 100 and rho[0] == 1.0 and rho[1] == pytest.approx(1.06)


@pytest.mark.parametrize(
    "field, value",
    [("horizon", -1.0), ("num_steps", 1), ("order", 2), ("iterations", 0), ("v_max", 0.05),
     ("a_max", 0.0), ("max_heading_deg", 95.0), ("rho_growth", 0.9), ("num_steps", 10.5),
     ("ellipse_a", float("nan")), ("max_obstacles", -1), ("heading_target_deg", 14.0),
     ("heading_target_deg", 0.0), ("heading_target_deg", float("nan"))],
)
def test_invalid_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        OptimizerConfig(**{field: value})


def test_from_dict_rejects_unknown_keys():
    assert OptimizerConfig.from_dict({"iterations": 50}).iterations == 50
    with pytest.raises(ValueError, match="iteratons"):
        OptimizerConfig.from_dict({"iteratons": 50})


def test_committed_yaml_matches_the_defaults():
    from mmpc.configs import shipped_config_dir

    path = shipped_config_dir("optimizer") / "default.yaml"
    assert OptimizerConfig.from_yaml(path) == OptimizerConfig()


def test_from_yaml_rejects_unknown_keys(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("iterations: 10\nrho_grwoth: 1.1\n")
    with pytest.raises(ValueError, match="rho_grwoth"):
        OptimizerConfig.from_yaml(path)
