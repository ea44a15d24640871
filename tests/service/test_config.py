"""Line and part configuration: the shipped files, strictness, overrides, hashing."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from service.config import (
    GENERATED_PANEL,
    ConfigError,
    LineConfig,
    load_line_config,
    load_part_spec,
)

ROOT = Path(__file__).resolve().parents[2]
LINE = ROOT / "configs" / "line.toml"


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_shipped_line_config_validates_and_lists_existing_parts():
    cfg = load_line_config(LINE)
    assert cfg.zenoh.multicast_scouting is False
    assert all(e.startswith("tcp/127.0.0.1:") for e in cfg.zenoh.listen)
    for p in cfg.part_spec_paths():
        spec = load_part_spec(p)
        assert spec.name == p.stem


def test_shipped_demo_part_is_generated_and_has_points():
    spec = load_part_spec(ROOT / "configs" / "parts" / "demo-panel.toml")
    assert spec.cad == GENERATED_PANEL
    assert len(spec.points) >= 3
    for cp in spec.points:
        assert abs(sum(c * c for c in cp.normal) - 1) < 1e-9
        assert cp.lower_mm < cp.upper_mm


def test_defaults_equal_an_empty_file(tmp_path):
    cfg = load_line_config(write(tmp_path, "line.toml", ""))
    assert cfg.effective() == LineConfig().effective()


@pytest.mark.parametrize(
    "text, where",
    [
        ("[line]\nnmae = 'x'\n", "line.nmae"),
        ("[line]\ntrigger_period_s = 0\n", "line.trigger_period_s"),
        ("[line]\nname = 'has space'\n", "line.name"),
        ("[zenoh]\nlisten = ['localhost']\n", "zenoh.listen"),
        ("[retention]\nrecord = 'some'\n", "retention.record"),
        ("[simulator]\ndefect_rate = 1.5\n", "simulator.defect_rate"),
        ("[simulator]\ndent_depth_mm = 0\n", "simulator.dent_depth_mm"),
        ("[simulator]\ndent_radius_mm = 500\n", "simulator.dent_radius_mm"),
        ("[simulator]\nyaw_range_deg = 270\n", "simulator.yaw_range_deg"),
        ("[simulator]\nposition_range_x_mm = -1\n", "simulator.position_range_x_mm"),
        ("[station]\nrig = 'depth'\n", "station.rig"),
        ("[station]\nguided_matching = 'sometimes'\n", "station.guided_matching"),
        ("[bogus]\n", "bogus"),
        ("[storage]\nmcap_rotate_mb = nan\n", "storage.mcap_rotate_mb"),
        ("[storage]\nurl = 'mysql://db/results'\n", "storage.url"),
        ("[storage]\nurl = 'runs/results.sqlite'\n", "storage.url"),
        ("[storage]\nurl = 'postgresql://db/results?sslmod=require'\n", "storage.url"),
    ],
)
def test_bad_line_files_fail_with_the_key(tmp_path, text, where):
    with pytest.raises(ConfigError, match=where.replace(".", r"\.")):
        load_line_config(write(tmp_path, "line.toml", text))


def test_not_toml_and_missing(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_line_config(write(tmp_path, "line.toml", "[line\n"))
    with pytest.raises(ConfigError, match="no such file"):
        load_line_config(tmp_path / "absent.toml")


def test_environment_then_flags_override(tmp_path):
    path = write(tmp_path, "line.toml", "[http]\nport = 8000\n")
    env = {
        "INSPECTION_DATA_DIR": "/srv/data",
        "INSPECTION_HTTP_PORT": "9001",
        "INSPECTION_ZENOH_CONNECT": "tcp/10.0.0.1:7447, tcp/10.0.0.2:7447",
        "UNRELATED": "x",
    }
    cfg = load_line_config(path, env=env)
    assert cfg.storage.data_dir == "/srv/data"
    assert cfg.http.port == 9001
    assert cfg.zenoh.connect == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    cfg2 = load_line_config(
        path, env=env, overrides={("http", "port"): 9002, ("line", "name"): None}
    )
    assert cfg2.http.port == 9002
    with pytest.raises(ConfigError, match="http.port"):
        load_line_config(path, env={"INSPECTION_HTTP_PORT": "eighty"})


def test_the_store_is_the_sqlite_file_unless_a_postgresql_url_is_given(tmp_path):
    path = write(tmp_path, "line.toml", "[storage]\ndata_dir = 'd'\n")
    assert load_line_config(path).storage.store_target() == Path("d") / "results.sqlite"
    url = "postgresql://insp:s3cret@db.plant:5432/results?sslmode=require"
    cfg = load_line_config(path, env={"INSPECTION_STORAGE_URL": url})
    assert cfg.storage.store_target() == url
    # The effective config goes into the logs and every recording: never the password.
    shown = cfg.effective()["storage"]["url"]
    assert shown == "postgresql://insp:***@db.plant:5432/results?sslmode=require"
    assert "s3cret" not in json.dumps(cfg.effective())
    off = load_line_config(path, env={"INSPECTION_STORAGE_URL": ""})
    assert off.storage.store_target() == Path("d") / "results.sqlite"


def test_a_bad_storage_url_is_told_without_its_password(tmp_path):
    path = write(tmp_path, "line.toml", "[storage]\nurl = 'mysql://u:s3cret@db/results'\n")
    with pytest.raises(ConfigError, match="a postgresql://") as err:
        load_line_config(path)
    assert "mysql://" in str(err.value) and "s3cret" not in str(err.value)
    path = write(tmp_path, "line.toml", "[storage]\nurl = 'postgresql://u:s%zz3cret@db/r'\n")
    with pytest.raises(ConfigError, match="not a valid PostgreSQL URL") as err:
        load_line_config(path)
    assert "s%zz3cret" not in str(err.value) and "s3cret" not in str(err.value)


def test_hash_follows_the_effective_values(tmp_path):
    a = load_line_config(write(tmp_path, "a.toml", "[http]\nport = 8000\n"))
    b = load_line_config(write(tmp_path, "b.toml", "# same values\n[http]\nport = 8000\n"))
    c = load_line_config(write(tmp_path, "c.toml", "[http]\nport = 8001\n"))
    assert a.hash() == b.hash() != c.hash()
    assert len(a.hash()) == 64


def test_installation_paths_are_relative_to_the_file(tmp_path):
    cfg = load_line_config(
        write(tmp_path, "line.toml", "[station]\nrig_calibration = 'rig.toml'\n")
    )
    assert cfg.rig_calibration_path() == tmp_path / "rig.toml"
    assert cfg.parts_path() == tmp_path / "parts"
    assert cfg.key("frames") == "insp/v1/line1/st1/frames"


PART = """
name = "bracket"
cad = "bracket.stl"
scale = 25.4
[[points]]
name = "p1"
position_mm = [0, 0, 1]
normal = [0, 0, 2]
lower_mm = -0.2
upper_mm = 0.3
radius_mm = 5
"""


def test_part_spec(tmp_path):
    spec = load_part_spec(write(tmp_path, "bracket.toml", PART))
    assert spec.points[0].normal == [0.0, 0.0, 1.0]
    assert spec.cad_path(tmp_path) == tmp_path / "bracket.stl"
    assert spec.registration.loss == "tukey"
    assert spec.tree.build_kwargs() == {}


@pytest.mark.parametrize(
    "change, match",
    [
        (("lower_mm = -0.2", "lower_mm = 0.4"), "lower_mm"),
        (("normal = [0, 0, 2]", "normal = [0, 0, 0]"), "normal"),
        (("radius_mm = 5", "radius_mm = -1"), "radius_mm"),
        (('cad = "bracket.stl"', 'cad = "generated:box"'), "generated"),
        (("scale = 25.4", "scale = 25.4\ncolour = 'red'"), "colour"),
        (('name = "p1"', 'name = "p 1"'), "points.0.name"),
    ],
)
def test_bad_part_specs(tmp_path, change, match):
    with pytest.raises(ConfigError, match=match):
        load_part_spec(write(tmp_path, "bracket.toml", PART.replace(*change)))


def test_a_spec_without_a_surface_table_gets_the_sequence_defaults(tmp_path):
    from inspection.surface import SurfaceParams
    from service.parts import measure_params

    plain = load_part_spec(write(tmp_path, "bracket.toml", PART))
    assert measure_params(plain).surface == SurfaceParams()
    table = "lower_mm = -0.3\nupper_mm = 0.2\nmin_area_mm2 = 25\nfails_part = false\n"
    text = f"{PART}\n[surface]\n{table}"
    own = load_part_spec(write(tmp_path, "bracket.toml", text))
    assert measure_params(own).surface == SurfaceParams(-0.3, 0.2, 25.0, False)


@pytest.mark.parametrize(
    "table, where",
    [
        ("lower_mm = 0.1", "surface.lower_mm"),
        ("upper_mm = 0", "surface.upper_mm"),
        ("min_area_mm2 = -5", "surface.min_area_mm2"),
        ("fails_part = 'no'", "surface.fails_part"),
        ("depth_mm = 1", "surface.depth_mm"),
    ],
)
def test_bad_surface_tables_fail_with_the_key(tmp_path, table, where):
    with pytest.raises(ConfigError, match=where.replace(".", r"\.")):
        load_part_spec(write(tmp_path, "bracket.toml", f"{PART}\n[surface]\n{table}\n"))


@pytest.mark.parametrize(
    "settings, view",
    [
        ("", (0.0, 0.0, 1.0)),  # tukey, the default: on
        ('loss = "cauchy"', None),  # a loss without a plateau: off unless asked
        ("seen_from_above = false", None),
        ('loss = "huber"\nseen_from_above = false', None),
    ],
)
def test_seen_from_above_follows_the_loss(tmp_path, settings, view):
    spec = load_part_spec(write(tmp_path, "bracket.toml", f"{PART}\n[registration]\n{settings}\n"))
    assert spec.registration.view_direction() == view


def test_seen_from_above_needs_tukey(tmp_path):
    text = f'{PART}\n[registration]\nloss = "l2"\nseen_from_above = true\n'
    with pytest.raises(ConfigError, match="seen_from_above needs loss 'tukey'"):
        load_part_spec(write(tmp_path, "bracket.toml", text))


def test_part_name_must_match_file(tmp_path):
    with pytest.raises(ConfigError, match="file name"):
        load_part_spec(write(tmp_path, "other.toml", PART))


def test_duplicate_point_names(tmp_path):
    text = PART + PART[PART.index("[[points]]") :]
    with pytest.raises(ConfigError, match="used twice"):
        load_part_spec(write(tmp_path, "bracket.toml", text))


def test_the_line_file_sets_every_simulator_key_and_the_ingest_uses_them():
    from service.line import Station

    path = Path(__file__).resolve().parents[2] / "configs" / "line.toml"
    cfg = load_line_config(path)
    text = path.read_text()
    written = tomllib.loads(text)["simulator"]
    # TOML has no null: a key whose default is "none" is shown in a comment.
    assert "\n# drift_point = " in text and "\n# parts = " in text
    assert set(written) | {"drift_point", "parts"} == set(type(cfg.simulator).model_fields)
    settings = Station.load(cfg, build_trees=False, warm_up=False).simulated_rig().settings
    sim = cfg.simulator
    assert (settings.dent_depth_mm, settings.dent_radius_mm, settings.yaw_range_deg) == (
        sim.dent_depth_mm, sim.dent_radius_mm, sim.yaw_range_deg,
    )  # fmt: skip
    assert settings.position_range_mm == (sim.position_range_x_mm, sim.position_range_y_mm)
    assert (settings.flip, settings.seed, settings.defect_rate) == (
        sim.flip, sim.seed, sim.defect_rate,
    )  # fmt: skip
    assert (settings.hole_shift_mm, settings.hole_radius_mm) == (
        sim.hole_shift_mm, sim.hole_radius_mm,
    )  # fmt: skip
    assert settings.dent_flat_mm == sim.dent_flat_mm


def test_the_belt_the_flash_and_the_slide_reach_the_simulator():
    """The line's defaults render as the nominal rig with the simulator's defaults (the
    frames of before); changed, the belt speed and the slide reach the rig rendered,
    the flash the render options."""
    from inspection.rig import Rig
    from inspection.simulate import RenderOptions
    from service.line import stages_for

    stages = stages_for(load_line_config(LINE))
    assert stages.rig.id == Rig.nominal().id
    assert stages.render.options == RenderOptions()
    changed = load_line_config(
        LINE,
        overrides={
            ("line", "conveyor_speed_mm_s"): 1500.0,
            ("projector", "flash_us"): 2000.0,
            ("projector", "pattern_seed"): 3,
        },
    )
    stages = stages_for(changed)
    assert stages.rig.conveyor.speed_mm_s == 1500.0
    assert stages.rig.projector.pattern.seed == 3
    assert stages.render.options.flash_us == 2000.0


@pytest.mark.parametrize(
    ("section", "text", "message"),
    [
        ("projector", "flash_us = 0.0", "greater than 0"),
        ("projector", "flash_us = 20000.0", "less than or equal to 10000"),
        ("projector", "flash_ms = 2.0", "Extra inputs are not permitted"),  # the old key
        ("simulator", "dent_flat_mm = 15.0", "dent_flat_mm"),
    ],
)
def test_flash_and_dent_keys_are_bounded(tmp_path, section, text, message):
    with pytest.raises(ConfigError, match=message):
        load_line_config(write(tmp_path, "line.toml", f"[{section}]\n{text}\n"))


@pytest.mark.parametrize(
    "text, message",
    [
        ('executor = "dask"\n', 'executor = "dask" needs dask_scheduler'),
        ('dask_scheduler = "local:2"\n', 'executor is "in-process"'),
        ('executor = "dask"\ndask_scheduler = "host:8786"\n', "is not a Dask address"),
        ('executor = "dask"\ndask_scheduler = "local:0"\n', "is not a Dask address"),
        ('executor = "threads"\n', "station.executor"),
    ],
)
def test_a_dask_executor_needs_a_valid_address(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        load_line_config(write(tmp_path, "line.toml", f"[station]\n{text}"))


def test_the_executor_is_in_process_unless_a_cluster_is_named(tmp_path):
    from service.config import DaskAddress

    assert load_line_config(LINE).station.dask_address() is None
    for address, want in (
        ("tcp://10.0.0.5:8786", DaskAddress(scheduler="tcp://10.0.0.5:8786")),
        ("local:3", DaskAddress(local_workers=3)),
    ):
        dask = {("station", "executor"): "dask", ("station", "dask_scheduler"): address}
        cfg = load_line_config(LINE, overrides=dask)
        assert cfg.station.dask_address() == want and str(want) == address
