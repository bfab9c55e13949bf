import pytest

from fmfusion_jax.config import PipelineConfig, load_config
from fmfusion_jax.errors import UserError


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


@pytest.mark.parametrize("override, fragment", [
    ("detection.every=1", "did you mean 'detections'"),
    ("detections.evry=1", "did you mean 'detections.every'"),
    ("detections.every=ten", "must be like 10"),
    ("label_fusion.mode=magic", "additive or bayes"),
    ("noequals", "expected section.key=value"),
])
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


@pytest.mark.parametrize("override, fragment", [
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
])
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
