"""Names in a workspace: control characters refused on the way in, escaped on the way out."""

import pytest
from click.testing import CliRunner

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.labels import Annotation
from dualhuman_builder.workspace import Workspace
from dualhuman_builder.workspace.workspace import printable

HOSTILE = ["T\x1b[2J", "a\nb", "tab\there", "bidi\u202eevil", "nul\x00", "bell\x07", "line\u2028sep"]


@pytest.mark.parametrize("name", HOSTILE)
def test_names_with_control_characters_are_refused(ws, name):
    with pytest.raises(WorkspaceError, match="contains control characters") as e:
        ws.add_take(name)
    assert "\x1b" not in str(e.value) and "control characters" in e.value.fix
    ws.add_take("T1")
    for call in (lambda: ws.add_actor(name, 1.7), lambda: ws.add_sequence("T1", name, 0, 5),
                 lambda: ws.add_sequence("T1", "s1", 0, 5, labels=(name,)),
                 lambda: ws.annotate([Annotation("T1", None, name, ("hug",))]),
                 lambda: ws.annotate([Annotation("T1", None, "ann", (name,))])):  # fmt: skip
        with pytest.raises(WorkspaceError, match="contains control characters"):
            call()
    assert ws.takes() == ["T1"] and ws.actors() == [] and ws.sequences("T1") == [] and ws.annotations() == []


def test_printable_escapes_only_what_a_terminal_would_act_on():
    assert printable("T\x1b[2J") == "T\\x1b[2J" and printable("bidi\u202eevil") == "bidi\\u202eevil"
    assert printable("café — Ünïcode ok [bold]") == "café — Ünïcode ok [bold]"


def test_status_prints_names_and_errors_escaped(tmp_path):
    from dualhuman_builder import cli

    root = tmp_path / "ws"
    with Workspace.init(root) as ws:
        ws.add_take("T1")
        ws.add_sequence("T1", "s1", 0, 5)

        def boom(out):
            raise RuntimeError("bad \x1b]0;title\x07 input")

        with pytest.raises(RuntimeError):
            ws.run_stage("sync", boom, take="T1", params={})
        # as a catalog written before names were checked may hold them
        ws.conn.execute("UPDATE takes SET name = ? WHERE name = 'T1'", ("T\x1b[31mred\x07",))
        ws.conn.execute("UPDATE sequences SET name = ?", ("s\u202e1\n",))
    for args in ([], ["--long"], ["--verify"]):
        r = CliRunner().invoke(cli.main, ["status", str(root), *args])
        assert r.exit_code == 0, r.output
        assert not {"\x1b", "\x07", "\u202e"} & set(r.output), repr(r.output)
        assert "T\\x1b[31mred\\x07" in r.output and "s\\u202e1\\n" in r.output
        if args != ["--verify"]:
            assert "bad \\x1b]0;title\\x07 input" in r.output
