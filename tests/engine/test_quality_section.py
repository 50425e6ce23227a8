"""The novel-view quality section of BENCHMARKS.md reads only its results JSON: the 64-px (``cpu``) tables, and
beside them the 256-px sets (``cpu256`` and ``cpu256-extrapolation``) against the floor, issue 47's goals and the PSNR
cost of surface-guided rendering and the CPU-seconds of one 256-px view."""

import json


def _result(protocol_set: str, model: str, rows: dict, guided: bool = False) -> dict:
    from omnirecon.provenance import provenance

    scenes = [{"name": n, "protocol": "dtu" if n.startswith("dtu") else "llff",
               "settings": {"3": {"mean": m, "views": [{"cpu_seconds": 8.0 if guided else 12.0}]}}}
              for n, m in rows.items()]
    return {"provenance": provenance(seed=0), "protocol_set": protocol_set, "model": {"name": model},
            "scenes": scenes, "means": {}, **({"guided": {"on": True}} if guided else {})}


def test_section_puts_256_px_beside_64_px_with_the_floor_and_goals(tmp_path):
    from bench.quality import result_name
    from bench.report.quality import section

    def write(pset, model, rows, guided=False):
        (tmp_path / result_name(pset, model, guided)).write_text(json.dumps(_result(pset, model, rows, guided)))

    write("cpu", "floor", {"fern": {"psnr": 18.0}})
    write("cpu", "ibrnet-tiny", {"fern": {"psnr": 19.0}})
    write("cpu256", "floor", {"fern": {"psnr": 17.0}, "dtu_scan24": {"psnr": 12.0, "psnr_masked": 14.0}})
    write("cpu256-extrapolation", "floor", {"fern": {"psnr": 15.0}, "dtu_scan24": {"psnr": 10.0, "psnr_masked": 9.0}})
    write("cpu256-extrapolation", "ibrnet-tiny", {"dtu_scan24": {"psnr": 11.0, "psnr_masked": 10.0}})  # full only
    write("cpu256", "ibrnet-tiny", {"fern": {"psnr": 19.0}})  # full sampling, fern only
    write("cpu256", "ibrnet-tiny", {"fern": {"psnr": 18.8}, "dtu_scan24": {"psnr": 13.0, "psnr_masked": 14.5}},
          guided=True)
    write("cpu256-extrapolation", "ibrnet-tiny", {"fern": {"psnr": 17.0}}, guided=True)
    text = section(tmp_path)
    assert "### At a 256-px long side" in text
    assert "| fern | 18.00 | 17.00 | 19.00 [+1.00] | 19.00 [+2.00] |" in text  # full sampling where both ran
    assert "| fern (extrapolation) | – | 15.00 | – | 17.00 [+2.00] `guided` |" in text
    assert "- ibrnet-tiny: fern +2.00 (met); DTU mask +0.50 (short); extrapolation +1.50 (met)" in text
    assert "| ibrnet-tiny | fern | 19.00 | 18.80 | -0.20 |" in text
    assert "| dtu_scan24 (extrapolation) | – | 10.00 (mask 9.00) | – | 11.00 (mask 10.00) [+1.00, mask +1.00] |" in text
    assert "| ibrnet-tiny | full sampling | 2 | 12.0 | 12.0-12.0 |" in text
    assert "| ibrnet-tiny | surface-guided | 3 | 8.0 | 8.0-8.0 |" in text
