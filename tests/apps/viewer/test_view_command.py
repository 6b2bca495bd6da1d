"""`sagonline view`: the command builds the session and the server, prints the URL and stops
cleanly on Ctrl+C; a bad scene ends in one line."""

from __future__ import annotations

import socket

import pytest

from sagonline.apps.cli import main
from sagonline.scene.io import write_ply
from tests.segment.test_clicks import iced_donut


@pytest.mark.parametrize(
    ("every", "shown", "line"),
    [((), 6, "rendering 6 views"), (("--every", "2"), 3, "rendering 3 of 6 views (every 2nd)")],
)
def test_view_serves_prints_its_url_and_stops_on_ctrl_c(
    tmp_path, capsys, monkeypatch, every, shown, line
):
    g, _ = iced_donut(40, 20)
    write_ply(tmp_path / "donut.ply", g)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    from sagonline.apps.viewer.app import ViewerApp

    apps, picked = [], []
    build = ViewerApp.__init__

    def keep(self, *args, **kwargs):
        build(self, *args, **kwargs)
        apps.append(self)

    def interrupt(_seconds):  # the panel while it serves: its last view chosen, then Ctrl+C
        apps[0].view_choice.value = apps[0].view_choice.options[-1]
        picked.append(apps[0].view_choice_index())
        raise KeyboardInterrupt

    monkeypatch.setattr(ViewerApp, "__init__", keep)
    monkeypatch.setattr("sagonline.apps.cli.view.time.sleep", interrupt)
    argv = [
        "view",
        str(tmp_path / "donut.ply"),
        "--orbit",
        "6",
        "--width",
        "64",
        "--height",
        "48",
        "--port",
        str(port),
        "--backend",
        "native",
        *every,
    ]
    assert main(argv) == 130
    out = capsys.readouterr()
    assert f"viewer at http://127.0.0.1:{port} ({shown} views rendered in" in out.out
    assert "no --cameras given" in out.err and line in out.err
    step = 6 // shown  # the panel numbers the session's views as `sagonline cameras` does
    expected = [f"{i}: orbit_{i:03d}" for i in range(0, 6, step)]
    assert list(apps[0].view_choice.options) == expected and picked == [shown - 1]


def test_view_of_a_missing_scene_is_one_line(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nothing.ply")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing.ply" in err[0]


def test_a_port_out_of_range_is_refused_at_once(capsys):
    """--port -1 or 70000 killed viser's server thread and the command waited forever."""
    for port in ("-1", "70000", "http"):
        with pytest.raises(SystemExit) as exc:
            main(["view", "scene.ply", "--port", port])
        assert exc.value.code == 2
        assert "--port" in capsys.readouterr().err


def test_a_taken_port_and_an_output_that_is_the_input_are_refused(tmp_path, capsys):
    g, _ = iced_donut(40, 20)
    scene = tmp_path / "donut.ply"
    write_ply(scene, g)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["view", str(scene), "--orbit", "6", "--port", str(port)]) == 2
        err = capsys.readouterr().err
        assert f"--port {port}: cannot serve on 127.0.0.1:{port}" in err
    assert main(["view", str(scene), "--out", str(scene)]) == 2
    assert "is one of the inputs" in capsys.readouterr().err


def test_serving_beyond_this_machine_is_said(capsys):
    from sagonline.apps.cli.view import warn_if_exposed

    warn_if_exposed("127.0.0.1")
    warn_if_exposed("localhost")
    assert capsys.readouterr().err == ""
    warn_if_exposed("0.0.0.0")
    assert "anyone who can reach this machine" in capsys.readouterr().err
