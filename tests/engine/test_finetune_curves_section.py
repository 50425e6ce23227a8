"""The fine-tuning curves section of BENCHMARKS.md: rows tuned with validation views that blend their nearest
sources (``--val-skip 0``) beside the same meshes' rows now."""


def test_the_val_skip_table_sets_each_gain_beside_the_same_meshs_row():
    from bench.report.finetune_curves import _skip0

    def row(mesh: str, psnr: list[float], skip: int) -> dict:
        return {"mesh": mesh, "val_skip": skip,
                "curve": [{"seconds": t, "psnr": p} for t, p in zip((0.0, 10.0, 60.0), psnr)]}

    now = {"walk": row("walk.ply", [10.0, 10.0, 10.0], 2), "other": row("b.ply", [20.0, 20.5, 21.0], 2)}
    before = {"rows": {"walk": row("walk.ply", [10.0, 9.7, 9.8], 0), "other": row("a.ply", [20.0, 20.0, 20.0], 0)},
              "provenance": {"commit": "cb282fbc6eb3"}}
    lines = _skip0(now, before)
    assert "| walk | whole image | -0.30 -> +0.00 | -0.20 -> +0.00 | – |" in lines
    assert not any(line.startswith("| other") for line in lines)  # another mesh: not the same comparison
    assert "`cb282fbc6eb3`" in lines[0]
    assert _skip0(now, None) == [] and _skip0({"walk": {**now["walk"], "val_skip": 0}}, before) == []
