import pytest

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
        (lambda t: t.replace('url = "vive+udp://0.0.0.0:8051"', 'url = "openvr://local"'), r"unknown URL scheme 'openvr'"),
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
