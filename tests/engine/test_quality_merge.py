"""``python -m bench quality`` for some scenes merges its rows into the results file (it used to overwrite it with
only those scenes): re-scored rows replaced, the others kept with the provenance of the run that scored them, the
means recomputed over the merged rows; a file of another checkpoint is replaced; the 256-px section names each run's
rows."""

import json

from omnirecon.engine.eval_report import collect


def _run(date: str, rows: dict[str, list[float]], ks=(3,), sha="aaaa", load=1.0) -> dict:
    """One run's results as ``evaluate`` assembles them: ``rows`` {scene: PSNR per target view} (LLFF protocol)."""
    records = [{"name": n, "protocol": "llff", "targets": list(range(len(v))), "settings": {}, "skipped": {}}
               for n, v in rows.items()]
    jobs = [{"record": rec, "k": k, "views": [{"index": i, "psnr": p, "seconds": 2.0 * k, "cpu_seconds": 1.0}
                                              for i, p in enumerate(rows[rec["name"]])]}
            for rec in records for k in ks]
    prov = {"commit": f"c{date[-2:]}", "date": date, "loadavg_1min": load, "seed": 0, "cores": 2}
    return collect(records, jobs, list(ks), {
        "provenance": prov, "model": {"name": "ibrnet-tiny", "sha256": sha}, "protocol_set": "cpu256-extrapolation",
        "geometry": False, "guided": {"on": True, "band": 0.03}, "non_protocol": {},
        "protocols": {"llff": {"name": "llff", "long_side": 256, "fixed_sources": ()}}})  # a tuple, as evaluate's


def test_a_run_for_some_scenes_keeps_the_other_rows_with_their_provenance(tmp_path):
    from bench.quality import result_name, save

    path = tmp_path / result_name("cpu256-extrapolation", "ibrnet-tiny", guided=True)
    save(path, _run("2026-12-02 04:50", {"dtu_scan24": [15.0, 16.0], "fern": [20.0, 21.0]}, ks=(3, 10), load=9.0))
    save(path, _run("2026-12-02 11:00", {"fern": [22.0, 22.0], "fox": [12.0, 13.0]}, load=1.5))
    r = json.loads(path.read_text())
    rows = {sc["name"]: sc["settings"] for sc in r["scenes"]}
    assert list(rows) == ["dtu_scan24", "fern", "fox"]
    assert rows["dtu_scan24"]["3"]["mean"]["psnr"] == 15.5 and rows["dtu_scan24"]["3"]["provenance"]["loadavg_1min"] == 9
    assert rows["fern"]["3"]["mean"]["psnr"] == 22.0  # re-scored: replaced
    assert rows["fern"]["3"]["provenance"]["date"] == "2026-12-02 11:00"
    assert rows["fern"]["10"]["provenance"]["date"] == "2026-12-02 04:50"  # K = 10 not re-scored: kept
    assert rows["fox"]["3"]["provenance"]["commit"] == "c00"
    assert r["means"]["llff"]["3"]["psnr"] == (15.5 + 22.0 + 12.5) / 3 and r["means"]["llff"]["3"]["scenes"] == 3
    assert r["means"]["llff"]["10"]["scenes"] == 2 and r["num_views"] == [3, 10]
    assert r["provenance"]["date"] == "2026-12-02 11:00"


def test_a_file_of_another_checkpoint_is_replaced_not_merged(tmp_path, capsys):
    from bench.quality import save

    path = tmp_path / "quality_cpu256-extrapolation_guided_ibrnet-tiny.json"
    save(path, _run("2026-12-02 04:50", {"dtu_scan24": [15.0, 16.0]}, sha="aaaa"))
    save(path, _run("2026-12-02 11:00", {"fern": [22.0, 22.0]}, sha="bbbb"))
    assert [sc["name"] for sc in json.loads(path.read_text())["scenes"]] == ["fern"]
    assert "checkpoint 'aaaa'" in capsys.readouterr().out


def test_the_256_px_section_names_the_rows_of_each_run(tmp_path):
    from bench.quality import save
    from bench.report.quality import _rows_256, provenance_256

    path = tmp_path / "quality_cpu256-extrapolation_guided_ibrnet-tiny.json"
    save(path, _run("2026-12-02 04:50", {"dtu_scan24": [15.0, 16.0], "fern": [20.0, 21.0]}, load=9.0))
    save(path, _run("2026-12-02 11:00", {"fox": [12.0, 13.0]}, load=1.5))
    text = "\n".join(provenance_256(_rows_256(tmp_path, ""), _rows_256(tmp_path, "_guided")))
    assert "- ibrnet-tiny (256 px, surface-guided; dtu_scan24 (extrapolation), fern (extrapolation)): commit `c50`; " \
           "date `2026-12-02 04:50`; loadavg_1min `9.0`" in text
    assert "- ibrnet-tiny (256 px, surface-guided; fox (extrapolation)): commit `c00`; date `2026-12-02 11:00`; " \
           "loadavg_1min `1.5`" in text
