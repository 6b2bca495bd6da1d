"""`sagonline view`: the command builds the session and the server, prints the URL and stops
cleanly on Ctrl+C; a bad scene ends in one line."""

from __future__ import annotations

import socket

from sagonline.apps.cli import main
from sagonline.scene.io import write_ply
from tests.segmenters.test_clicks import iced_donut


def test_view_serves_prints_its_url_and_stops_on_ctrl_c(tmp_path, capsys, monkeypatch):
    g, _ = iced_donut(40, 20)
    write_ply(tmp_path / "donut.ply", g)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def interrupt(_seconds):
        raise KeyboardInterrupt

    monkeypatch.setattr("sagonline.apps.cli.view.time.sleep", interrupt)
    argv = ["view", str(tmp_path / "donut.ply"), "--orbit", "6", "--width", "64", "--height",
            "48", "--port", str(port), "--backend", "native"]  # fmt: skip
    assert main(argv) == 130
    out = capsys.readouterr()
    assert f"viewer at http://127.0.0.1:{port} (6 views rendered in" in out.out
    assert "no --cameras given" in out.err


def test_view_of_a_missing_scene_is_one_line(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nothing.ply")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing.ply" in err[0]
