import dataclasses
from pathlib import Path

import pytest
import yaml

from fmfusion_jax.config import PipelineConfig, load_config
from fmfusion_jax.engine import step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.errors import UserError
from fmfusion_jax.mapping.engine_configs import build_map_config


def test_packaged_configs_load_with_paper_defaults():
    scannet = load_config("scannet")
    assert scannet.tsdf.voxel_size == pytest.approx(4.0 / 256)
    assert scannet.detections.every == 10
    assert scannet.association.threshold == 0.5
    assert scannet.refinement.merge_similarity == 0.15
    subsampled = load_config("scannet-subsampled")
    assert subsampled.detections.every == 1  # inherits the rest through `base:`
    assert subsampled.tsdf.sdf_trunc == scannet.tsdf.sdf_trunc
    scenenn = load_config("scenenn")
    assert (scenenn.detections.every, scenenn.refinement.remove_missed) == (5, 8)


def test_overrides_are_typed_and_applied():
    config = load_config("scannet", ["label_fusion.mode=bayes", "detections.every=3", "tsdf.voxel_size=0.02"])
    assert config.label_fusion.mode == "bayes"
    assert config.detections.every == 3
    assert config.tsdf.voxel_size == 0.02


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("detection.every=1", "did you mean 'detections'"),
        ("detections.evry=1", "did you mean 'detections.every'"),
        ("detections.every=ten", "'detections.every' must be a valid integer \\(default 10\\), got 'ten'"),
        ("label_fusion.mode=magic", "'additive' or 'bayes'"),
        ("tsdf=3", "expected section.key=value"),
        ("noequals", "expected section.key=value"),
    ],
)
def test_bad_overrides_are_one_line_errors(override, fragment):
    with pytest.raises(UserError, match=fragment):
        load_config("scannet", [override])


def test_unknown_config_file(tmp_path):
    with pytest.raises(UserError, match="not found"):
        load_config(str(tmp_path / "missing.yaml"))
    bad = tmp_path / "bad.yaml"
    bad.write_text("tsdf:\n  voxel_sise: 0.01\n")
    with pytest.raises(UserError, match="voxel_size"):
        load_config(str(bad))


def test_config_round_trips_through_yaml(tmp_path):
    config = load_config("scannet-subsampled", ["refinement.enabled=false"])
    path = tmp_path / "used.yaml"
    path.write_text(config.to_yaml())
    assert load_config(str(path)) == config
    assert PipelineConfig() == load_config(None)


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("refinement.merge_every=0", "merge_every"),
        ("refinement.geometry_fusion_every=0", "geometry_fusion_every"),
        ("detections.max_detections=0", "max_detections"),
        ("association.pixel_stride=0", "pixel_stride"),
        ("tsdf.block_size=0", "block_size"),
        ("tsdf.block_size=7", "block_size"),
        ("tsdf.bounds_margin=-10", "bounds_margin"),
        ("detections.depth_percentiles=[0.9,0.1]", "depth_percentiles"),
        ("export.transfer_radius=-1", "transfer_radius"),
        ("tsdf.voxel_size=[1", "not valid YAML"),
    ],
)
def test_out_of_range_values_are_one_line_errors_naming_the_knob(override, fragment):
    """Values that used to fail deep inside the run (ZeroDivisionError, JAX shape errors) or give a wrong map
    silently are refused when the config is read."""
    with pytest.raises(UserError, match=fragment):
        load_config("scannet", [override])


def test_missing_likelihood_file_is_a_user_error(tmp_path):
    from fmfusion_jax.labels import read_likelihood_csv

    with pytest.raises(UserError, match="cannot read the likelihood matrix"):
        read_likelihood_csv(tmp_path / "nonexistent.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(UserError, match="empty"):
        read_likelihood_csv(tmp_path / "empty.csv")


def test_the_schema_is_the_one_definition_of_every_knob():
    """docs/config.md is generated from the schema; configs/scannet.yaml sets (and documents) every knob, with
    the schema's defaults but the layout."""
    from fmfusion_jax.config import config_reference_markdown, config_schema, resolve_config_path

    docs = Path(__file__).resolve().parents[1] / "docs" / "config.md"
    assert docs.read_text() == config_reference_markdown() + "\n", "regenerate docs/config.md from the schema"
    written = yaml.safe_load(resolve_config_path("scannet").read_text())
    schema = config_schema()
    assert {s: set(keys) for s, keys in schema.items()} == {s: set(written[s]) for s in schema}
    defaults, scannet = PipelineConfig().to_dict(), load_config("scannet").to_dict()
    scannet["dataset"]["layout"] = defaults["dataset"]["layout"]
    assert scannet == defaults
    assert all(
        info["doc"] and info["kind"] in ("shape", "engine", "host") for knobs in schema.values() for info in knobs.values()
    )


def test_values_set_from_python_are_checked_too():
    from pydantic import ValidationError

    from fmfusion_jax.config import config_from_dict

    config = load_config("scannet")
    with pytest.raises(ValidationError):
        config.refinement.merge_every = 0
    with pytest.raises(ValidationError, match="must exceed tsdf.voxel_size"):
        config.tsdf.sdf_trunc = 0.001  # in range alone, not with the voxel size
    unchecked = config.model_copy(update={"tsdf": config.tsdf.model_copy(update={"sdf_trunc": 0.001})})
    with pytest.raises(UserError, match="sdf_trunc"):
        config_from_dict(unchecked.to_dict(), "config")


def test_each_engine_knob_has_one_default_the_schemas():
    """The engine's configs carry no default of their own: `FusionConfig` has none, and `MapConfig`'s defaults are
    what the translator makes of the default config (all but the block index, which comes from the scene's bounds)."""
    assert all(
        field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING
        for field in dataclasses.fields(step.FusionConfig)
    )
    from_schema = build_map_config(PipelineConfig(), (0.0, 0.0, 0.0), (4.0, 4.0, 3.0), 480, 640)
    engine_default = MapConfig()
    differing = {
        field.name
        for field in dataclasses.fields(MapConfig)
        if getattr(from_schema, field.name) != getattr(engine_default, field.name)
    }
    assert differing <= {"grid_origin", "grid_shape"}, differing
    # and the schema's values do reach it: a changed knob changes the engine config
    changed = PipelineConfig().model_copy(update={"tsdf": PipelineConfig().tsdf.model_copy(update={"block_capacity": 4096})})
    assert build_map_config(changed, (0.0, 0.0, 0.0), (4.0, 4.0, 3.0), 480, 640).block_capacity == 4096
