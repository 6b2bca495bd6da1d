"""`sagonline view`: the command builds the session and the server, prints the URL and stops
cleanly on Ctrl+C; a bad scene ends in one line."""

from __future__ import annotations

import socket

import pytest

from sagonline.apps.cli import main
from sagonline.scene.io import write_ply
from tests.segment.test_clicks import iced_donut


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve_until_ctrl_c(monkeypatch, argv: list[str], on_serve=None) -> list:
    """`main(argv)` for `sagonline view`, Ctrl+C pressed once it serves (after
    `on_serve(app)`); its exit code 130 checked; returns the ViewerApp it built, in a list."""
    from sagonline.apps.viewer.app import ViewerApp

    apps = []
    build = ViewerApp.__init__

    def keep(self, *args, **kwargs):
        build(self, *args, **kwargs)
        apps.append(self)

    def interrupt(_seconds):
        if on_serve is not None:
            on_serve(apps[0])
        raise KeyboardInterrupt

    monkeypatch.setattr(ViewerApp, "__init__", keep)
    monkeypatch.setattr("sagonline.apps.cli.view.time.sleep", interrupt)
    assert main(argv) == 130
    return apps


@pytest.mark.parametrize(
    ("every", "shown", "line"),
    [((), 6, "rendering 6 views"), (("--every", "2"), 3, "rendering 3 of 6 views (every 2nd)")],
)
def test_view_serves_prints_its_url_and_stops_on_ctrl_c(
    tmp_path, capsys, monkeypatch, every, shown, line
):
    g, _ = iced_donut(40, 20)
    write_ply(tmp_path / "donut.ply", g)
    port, picked = free_port(), []

    def choose_last_view(app):  # the panel while it serves: its last view chosen
        app.view_choice.value = app.view_choice.options[-1]
        picked.append(app.view_choice_index())

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
    apps = serve_until_ctrl_c(monkeypatch, argv, choose_last_view)
    out = capsys.readouterr()
    assert f"viewer at http://127.0.0.1:{port} ({shown} views rendered in" in out.out
    assert "no --cameras given" in out.err and line in out.err
    step = 6 // shown  # the panel numbers the session's views as `sagonline cameras` does
    expected = [f"{i}: orbit_{i:03d}" for i in range(0, 6, step)]
    assert list(apps[0].view_choice.options) == expected and picked == [shown - 1]


def test_view_takes_the_cameras_found_beside_the_scene(tmp_path, capsys, monkeypatch):
    """No --cameras, the scene's camera file beside it: its views are served (the panel's
    names are the file's), the command says where they came from, and Export records the file."""
    from tests.fixtures import own_scene

    folder, _, cams, _ = own_scene(tmp_path / "fit", views=4)
    scene = str(folder / "point_cloud.ply")
    argv = ["view", scene, "--port", str(free_port()), "--backend", "native"]
    apps = serve_until_ctrl_c(monkeypatch, argv)
    err = capsys.readouterr().err
    assert f"cameras of {folder}/transforms.json" in err
    assert "(found beside the scene; --cameras none: an orbit around it)" in err
    assert list(apps[0].view_choice.options) == [f"{i}: {c.name}" for i, c in enumerate(cams)]
    assert apps[0].info["cameras"] == str(folder / "transforms.json")


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
