"""Scene files: parsing, overrides and errors naming the bad key."""
import pytest
import yaml

from inject import DEFAULT_SCENE, SceneError, apply_overrides, load_scene_file, parse_scene


def test_default_scene_parses():
    scene = parse_scene(DEFAULT_SCENE)
    assert scene.detector.shape == (4000, 4072)
    assert scene.satellites[0].track.length is None


def test_overrides_reach_nested_keys_and_list_items():
    raw = apply_overrides(DEFAULT_SCENE, ["detector.nx=512", "detector.ny=400",
                                          "satellites.0.mag=6.5", "satellites.0.track.length=90",
                                          "stars=false", "band=r"])
    scene = parse_scene(raw)
    assert scene.detector.shape == (400, 512)
    assert scene.satellites[0].mag == 6.5 and scene.satellites[0].track.length == 90
    assert scene.stars is None and scene.band == "r"
    assert DEFAULT_SCENE["detector"] == {"type": "itl"}  # the default is not modified


@pytest.mark.parametrize("override,needle", [
    ("satellites.0.height=-3", "satellites[0]: height_km=-3.0"),
    ("satellites.0.height=abc", "satellites[0].height='abc'"),
    ("satellites.0.shape.type=cone", "shape.type='cone'"),
    ("satellites.0.colour=red", "satellites[0]: unknown keys ['colour']"),
    ("zenith=95", "zenith=95"),
    ("band=w", "band='w'"),
    ("seed=0", "seed=0"),
    ("detector.type=mystery", "detector.type='mystery'"),
    ("detector.nx=-4", "detector.nx=-4"),
    ("satellites.3.mag=1", "no list item satellites.3"),
    ("noise=maybe", "noise='maybe'"),
    ("satellites.0.mag=.nan", "satellites[0].mag=nan: must be finite"),
])
def test_bad_values_name_their_key(override, needle):
    with pytest.raises(SceneError) as info:
        parse_scene(apply_overrides(DEFAULT_SCENE, [override]))
    assert needle in str(info.value)


def test_missing_track_key():
    raw = apply_overrides(DEFAULT_SCENE, [])
    del raw["satellites"][0]["track"]["angle"]
    with pytest.raises(SceneError, match=r"satellites\[0\].track: missing keys \['angle'\]"):
        parse_scene(raw)


def test_scene_file_is_loaded_safely(tmp_path):
    evil = tmp_path / "evil.yaml"
    evil.write_text("seed: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(SceneError, match="not valid YAML"):
        load_scene_file(evil)
    with pytest.raises(SceneError, match="cannot read"):
        load_scene_file(tmp_path / "missing.yaml")
    listy = tmp_path / "list.yaml"
    listy.write_text(yaml.safe_dump([1, 2]))
    with pytest.raises(SceneError, match="must be a mapping"):
        load_scene_file(listy)


def test_a_field_without_the_traced_pupil_is_refused():
    """``field:`` says where the CCD sits for ``pupil: rubin``; with the annulus it would be
    ignored (``inject profile`` refuses ``--field-angle`` without ``--pupil rubin`` too)."""
    raw = dict(DEFAULT_SCENE, field={"angle": 1.2, "position_angle": 40})
    with pytest.raises(SceneError, match=r"^field\.angle=1\.2: only with pupil: rubin") as info:
        parse_scene(raw)
    assert "\n" not in str(info.value)
    assert parse_scene(dict(raw, pupil="rubin")).field == (1.2, 40.0)
