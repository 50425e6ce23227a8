import json

import torch

from omnirecon.cli import main


def test_doctor_reports_every_component(capsys):
    assert main(["doctor", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert {"torch", "CUDA", "EGL rasterization (moderngl)", "Chromium (browser tests)",
            "MP4 video (imageio-ffmpeg)", "shipped checkpoints"} <= set(rows)
    assert all(r["status"] in ("ok", "fallback", "missing") for r in rows.values())
    assert rows["torch"]["status"] == "ok" and torch.__version__ in rows["torch"]["detail"]
    assert (rows["CUDA"]["status"] == "ok") == torch.cuda.is_available()
    # every non-ok row says what happens without it
    assert all(r["consequence"] for r in rows.values() if r["status"] != "ok")


def test_doctor_table(capsys):
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "omnirecon doctor" in out and "EGL" in out
