import pytest
from click.testing import CliRunner

from dualhuman_builder.cli import main
from dualhuman_builder.errors import RigError
from dualhuman_builder.resources import RIGS_DIR
from dualhuman_builder.rig import load_rig


def test_example_rigs_load():
    studio = load_rig(RIGS_DIR / "studio.toml")
    assert studio.name == "studio" and [s.scheme for s in studio.sources] == ["mvn+udp", "vive+udp", "xbus", "mti+can"]
    a, b = studio.actors
    assert (a.character, b.character) == (0, 1) and a.source == b.source == "suits"
    assert a.trackers["LHR-A0000001"] == "Pelvis" and len(b.trackers) == 6
    assert studio.mapping.bone_of("LeftHand") == "wrist.L" and len(studio.sha256) == 64
    sim = load_rig(RIGS_DIR / "sim.toml")
    assert sim.source("scene").url == "sim://handshake?seed=3"


def _rig(tmp_path, edit):
    text = edit((RIGS_DIR / "studio.toml").read_text())
    (tmp_path / "mvn_anny.toml").write_text((RIGS_DIR / "mvn_anny.toml").read_text())
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace('"LHR-A0000003" = "LeftHand"', '"LHR-A0000003" = "LeftPalm"'),
         r"tracker 'LHR-A0000003' is on unknown MVN segment 'LeftPalm'"),
        (lambda t: t.replace('"LHR-B0000001"', '"LHR-A0000001"'), r"tracker 'LHR-A0000001' is worn by both 'actor-a' and 'actor-b'"),
        (lambda t: t.replace("character = 1", "character = 0"), r"share one MVN character ID"),
        (lambda t: t.replace("character = 1", "character = 300"), r"character must be an MVN character ID 0-255"),
        (lambda t: t.replace('url = "vive+udp://0.0.0.0:8051', 'url = "openvr://local'), r"unknown URL scheme 'openvr'"),
        (lambda t: t.replace('source = "suits"\ncharacter = 1', 'source = "suit"\ncharacter = 1'), r"uses source 'suit', which the rig does not define"),
        (lambda t: t.replace('name = "studio"', ""), r"needs a \[rig\] table with a non-empty name"),
        (lambda t: t.replace("[[sources]]", "[[sources]", 1), r"not valid TOML"),
        (lambda t: t.replace('mapping = "mvn_anny.toml"', 'mapping = "absent.toml"'), r"segment mapping 'absent.toml' not found beside the rig"),
    ],
)  # fmt: skip
def test_bad_rigs_are_rejected_with_the_reason(tmp_path, edit, message):
    path = _rig(tmp_path, edit)
    with pytest.raises(RigError, match=message) as e:
        load_rig(path)
    assert e.value.fix and e.value.path is not None


def test_rig_whose_mapping_names_an_unknown_bone(tmp_path):
    path = _rig(tmp_path, lambda t: t)
    m = tmp_path / "mvn_anny.toml"
    m.write_text(m.read_text().replace('bone = "upperleg01.L"', 'bone = "thigh.L"'))
    with pytest.raises(RigError, match="unknown anny bone 'thigh.L'") as e:
        load_rig(path)
    assert e.value.path == m and "dualhuman body info --bones" in e.value.fix


def test_the_example_studio_names_its_senders_and_trackers():
    studio = load_rig(RIGS_DIR / "studio.toml")
    assert studio.warnings() == [] and load_rig(RIGS_DIR / "sim.toml").warnings() == []
    suits, trackers = studio.source("suits"), studio.source("trackers")
    assert suits.query["allow"] and trackers.query["allow"]
    assert set(trackers.query["serials"].split(",")) == {s for a in studio.actors for s in a.trackers}


@pytest.mark.parametrize(
    "edit, warnings",
    [
        (lambda t: t.replace("?allow=192.168.10.11", ""), ["source 'suits' listens on every interface"]),
        (lambda t: t.replace("0.0.0.0:9763?allow=192.168.10.11", "[::]:9763"),
         ["source 'suits' listens on every interface"]),
        (lambda t: t.replace("0.0.0.0:9763?allow=192.168.10.11", "192.168.10.2:9763"), []),  # one interface
        (lambda t: t.replace("allow=192.168.10.12&serials=", "serials="),
         ["source 'trackers' listens on every interface"]),
        (lambda t: t.replace("&serials=LHR-A0000001,", "&serials=").replace(",LHR-B0000006", ""),
         ["tracker 'LHR-A0000001' worn by 'actor-a' is in no serials=", "tracker 'LHR-B0000006' worn by 'actor-b'"]),
        (lambda t: t.replace("allow=192.168.10.12&", "allow=&"), ["source 'trackers' listens on every interface"]),
    ],
)  # fmt: skip
def test_rig_warnings_for_open_udp_sources_and_unlisted_trackers(tmp_path, edit, warnings):
    rig = load_rig(_rig(tmp_path, edit))
    got = rig.warnings()
    assert len(got) == len(warnings) and all(g.startswith(w) for g, w in zip(got, warnings)), got


def test_rig_check_prints_the_warnings(tmp_path):
    path = _rig(tmp_path, lambda t: t.replace("?allow=192.168.10.11", "").replace(
        "allow=192.168.10.12&serials=LHR-A0000001,LHR-A0000002,LHR-A0000003,LHR-A0000004,LHR-A0000005,LHR-A0000006,"
        "LHR-B0000001,LHR-B0000002,LHR-B0000003,LHR-B0000004,LHR-B0000005,LHR-B0000006", "allow=192.168.10.12"))
    r = CliRunner().invoke(main, ["rig", "check", str(path)])
    assert r.exit_code == 0 and "rig 'studio' is valid" in r.output
    warnings = [line for line in r.output.splitlines() if line.startswith("warning: ")]
    assert len(warnings) == 2
    assert "source 'suits' listens on every interface (mvn+udp://0.0.0.0:9763) without allow=" in warnings[0]
    assert "add serials=LHR-A0000001,LHR-A0000002," in warnings[1]
    r = CliRunner().invoke(main, ["rig", "check", str(RIGS_DIR / "studio.toml")])
    assert r.exit_code == 0 and "warning" not in r.output


def test_capture_with_a_rig_prints_its_warnings_first(tmp_path):
    path = _rig(tmp_path, lambda t: t.replace("?allow=192.168.10.11", "")
                .replace("url = \"xbus:///dev/ttyUSB0?baud=921600\"", "url = \"xbus:///nonexistent/ttyUSB9\""))  # fmt: skip
    r = CliRunner().invoke(main, ["capture", "--rig", str(path), "--take", "T", "--out", str(tmp_path / "t.mcap"),
                                  "--duration", "0.2"])  # fmt: skip
    assert "warning: source 'suits' listens on every interface" in r.stderr
    assert r.exit_code != 0  # the rig's serial port does not exist here
