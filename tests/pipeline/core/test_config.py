import dataclasses
import re

import pytest

from pipeline.core.config import field_docs, load_config, parse_override
from pipeline.core.errors import ConfigError
from pipeline.core.sections import SHARED_SECTIONS, schema
from stages import STAGES
from tests.support.toy_stages import make_stages

SCHEMA = schema(make_stages())


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["double.factr=3"], "unknown key double.factr: section [double] has factor"),
        (["double.factor=2.5"], "double.factor = 2.5 has the wrong type: expected an integer"),
        (["double.factor=0"], "double.factor = 0 is out of range: allowed [1, 100]"),
        (["ingest.scale='big'"], "ingest.scale = 'big' has the wrong type: expected a number"),
        (
            ["ingest.fail=maybe"],
            "ingest.fail = 'maybe' is not allowed: use one of 'no', 'raise', 'user', 'sigkill', 'diskfull', "
            "'sleep', 'stubborn'",
        ),
        (["mesh.voxels=3"], "unknown section [mesh]"),
        (["board.marker_mm=40"], "board.marker_mm = 40.0 must be smaller than board.square_mm = 30.0"),
        (["light.area_size=0"], "light.area_size = 0.0 is out of range: allowed (0, inf]"),
        (["light.area_position=[1, 2]"], "light.area_position = [1, 2] needs exactly 3 items"),
        (["nodot=3"], "override 'nodot=3' must look like section.key=value"),
        # NaN passes every range check and no setting means infinity: both are refused.
        (["board.square_mm=nan"], "board.square_mm = nan is not a finite number"),
        (["board.square_mm=inf"], "board.square_mm = inf is not a finite number"),
        (["ingest.scale=nan"], "ingest.scale = nan is not a finite number"),
        (["light.environment_radiance=[1, nan, inf]"], "light.environment_radiance[1] = nan is not a finite number"),
        # a negative radiance has no physical meaning; the fits would bend the material to it
        (["light.area_radiance=[6, -1, 6]"], "light.area_radiance[1] = -1.0 is out of range: allowed [0, 1e+09]"),
        # 3e38 rendered NaN in float32 and ended fit_material on a non-finite result
        (["light.environment_radiance=[3e38, 1, 1]"], "light.environment_radiance[0] = 3e+38 is out of range"),
    ],
)
def test_bad_overrides_name_key_value_and_allowed(presets_dir, overrides, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_config(SCHEMA, None, "standard", overrides, presets_dir)


def test_error_names_the_file_that_set_the_value(tmp_path, presets_dir):
    capture = tmp_path / "cap"
    capture.mkdir()
    (capture / "capture.toml").write_text("[double]\nfactor = 1000\n")
    with pytest.raises(ConfigError, match=f"set in .*{capture / 'capture.toml'}"):
        load_config(SCHEMA, capture, "standard", [], presets_dir)


def test_invalid_toml_names_the_file(tmp_path, presets_dir):
    capture = tmp_path / "cap"
    capture.mkdir()
    (capture / "capture.toml").write_text("[double\n")
    with pytest.raises(ConfigError, match="capture.toml: invalid TOML"):
        load_config(SCHEMA, capture, "standard", [], presets_dir)


def test_unknown_preset_lists_the_known_ones(presets_dir):
    with pytest.raises(ConfigError, match="unknown preset 'fast': choose one of draft, standard"):
        load_config(SCHEMA, None, "fast", [], presets_dir)


def test_override_values_are_toml_with_bare_string_fallback():
    assert parse_override("a.b=3") == ("a", "b", 3)
    assert parse_override("a.b=[1, 2.5]") == ("a", "b", [1, 2.5])
    assert parse_override("a.b=dual") == ("a", "b", "dual")
    assert parse_override("a.b='x=y'") == ("a", "b", "x=y")


def test_int_is_accepted_where_a_float_is_expected(presets_dir):
    config = load_config(SCHEMA, None, "standard", ["ingest.scale=2"], presets_dir)
    assert config["ingest"].scale == 2.0 and isinstance(config["ingest"].scale, float)


@pytest.mark.parametrize(
    "override, message",
    [
        ("light.environment_map='images'", "is a folder: name a file (.exr,"),
        ("light.environment_map='capture.toml'", "is not a file this setting reads: name a file (.exr,"),
        ("cameras.source='images'", "is a folder without cameras.bin or cameras.txt"),
        ("cameras.source='capture.toml'", "is not a file this setting reads: name a file (.bin, .txt, .xml)"),
        ("mesh.source='images'", "is a folder: name a file (.ply, .obj)"),
        ("calibrate.known_intrinsics='capture.toml'", "name a file (.json, .yml, .yaml, .xml)"),
    ],
)
def test_a_file_setting_naming_a_folder_or_another_kind_of_file_is_refused(tmp_path, override, message):
    """Refused before anything runs, not by the stage that reads it after the others ran."""
    capture = tmp_path / "cap"
    (capture / "images").mkdir(parents=True)
    (capture / "capture.toml").write_text("")
    with pytest.raises(ConfigError, match=re.escape(override.split("=")[0] + " = ") + ".*" + re.escape(message)):
        load_config(schema(STAGES), capture, "standard", [override])
    (capture / "model").mkdir()
    (capture / "model" / "cameras.bin").write_bytes(b"")
    load_config(schema(STAGES), capture, "standard", ["cameras.source='model'"])  # a COLMAP model's folder


@pytest.mark.parametrize("source, folder", [("user", "masks"), ("background", "background")])
def test_a_forced_mask_source_without_its_files_is_refused(tmp_path, source, folder):
    capture = tmp_path / "cap"
    capture.mkdir()
    (capture / "capture.toml").write_text("")
    with pytest.raises(ConfigError, match=re.escape(f"masks.source = '{source}' but the capture's {folder}/ folder")):
        load_config(schema(STAGES), capture, "standard", [f"masks.source='{source}'"])
    (capture / folder).mkdir()
    (capture / folder / "view_000.png").write_bytes(b"")
    load_config(schema(STAGES), capture, "standard", [f"masks.source='{source}'"])


@pytest.mark.parametrize(
    "bounds, message",
    [
        ('["none_such"]', "fit_material.bounds: 'none_such' is not name=lower:upper"),
        ('["eta=2:1.5"]', "fit_material.bounds: 'eta=2:1.5' has lower >= upper"),
        ('["colour=0:1"]', "fit_material.bounds names 'colour', no material parameter"),
    ],
)
def test_the_fits_bounds_are_refused_as_the_settings_load(bounds, message):
    """Not when fit_material starts, after every stage before it ran."""
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_config(schema(STAGES), None, "standard", [f"fit_material.bounds={bounds}"])
    load_config(schema(STAGES), None, "standard", ['fit_material.bounds=["eta=1.3:1.6"]'])


def test_real_presets_load_with_the_real_stages():
    for preset in ("draft", "standard", "final"):
        load_config(schema(STAGES), None, preset)


@pytest.mark.parametrize("name, cls", sorted({**SHARED_SECTIONS, **schema(STAGES)}.items()))
def test_every_field_of_every_real_section_is_documented(name, cls):
    docs = field_docs(cls)
    missing = [f.name for f in dataclasses.fields(cls) if f.name not in docs]
    assert not missing, f"[{name}] fields without a docstring: {missing}"
    assert cls.__doc__ and not cls.__doc__.startswith(cls.__name__ + "(")
