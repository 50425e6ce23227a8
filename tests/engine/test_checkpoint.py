import torch

from omnirecon.engine.checkpoint import load_checkpoint, load_optimizer_state, save_checkpoint
from omnirecon.models.registry import build_model


def test_round_trip_weights_config_and_optimizer(tmp_path):
    torch.manual_seed(0)
    model = build_model("gpnr-tiny", {"num_samples": 8, "dim": 32, "mlp_dim": 32, "layers": [1, 1, 1]})
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    loss = sum(p.square().sum() for p in model.parameters())
    loss.backward()
    opt.step()
    save_checkpoint(tmp_path / "ck", model, "gpnr-tiny", step=7, optimizer=opt)
    model2, meta = load_checkpoint(tmp_path / "ck")
    assert meta["step"] == 7 and model2.cfg == model.cfg
    for (k, a), (_, b) in zip(model.state_dict().items(), model2.state_dict().items()):
        assert torch.equal(a, b), k
    opt2 = torch.optim.AdamW(model2.parameters(), lr=1e-3)
    load_optimizer_state(tmp_path / "ck", opt2)
    s1, s2 = opt.state_dict(), opt2.state_dict()
    for pid in s1["state"]:
        for name in s1["state"][pid]:
            assert torch.equal(torch.as_tensor(s1["state"][pid][name]), torch.as_tensor(s2["state"][pid][name]))
    assert not list(tmp_path.glob("ck/.*"))  # no temporary files left


def test_load_model_takes_the_weights_trained_nearest_the_render_size(tmp_path):
    """A checkpoint with ``sizes/256/``: ``load_model`` for a 64- or 128-px render keeps the folder's own weights
    (trained at 64 px), for a 200-px one loads the 256-px weights and says so in ``info``; without ``sizes/`` every
    size loads the own weights."""
    from omnirecon.engine.machine import load_model

    cfg = {"num_samples": 8, "dim": 32, "mlp_dim": 32, "layers": [1, 1, 1]}
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "ck", build_model("gpnr-tiny", cfg), "gpnr-tiny", step=5, train_config={"resolution": 64})
    _, info = load_model(tmp_path / "ck", None, long_side=200)
    assert info["checkpoint"] == str(tmp_path / "ck") and "trained_long_side" not in info
    torch.manual_seed(1)
    save_checkpoint(tmp_path / "ck" / "sizes" / "256", build_model("gpnr-tiny", cfg), "gpnr-tiny", step=9,
                    train_config={"resolution": 256})
    for side, step in ((64, 5), (128, 5), (None, 5), (200, 9), (1008, 9)):
        net, info = load_model(tmp_path / "ck", None, long_side=side)
        assert info["step"] == step, side
    assert info["checkpoint"] == str(tmp_path / "ck" / "sizes" / "256") and info["trained_long_side"] == 256
