"""Training end to end on tiny pairs: every stage runs, checkpoints resume exactly, torchrun DDP."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from drivingscene.data import save_frame_pair
from drivingscene.models.depth import DepthConfig
from drivingscene.models.model import ModelConfig
from drivingscene.models.residual_flow import FlowConfig
from drivingscene.train.config import TrainConfig
from drivingscene.train.trainer import train
from tests.factories import make_pair

TINY_MODEL = ModelConfig(
    depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)),
    flow=FlowConfig(channels=(8, 8, 16, 16), hidden=8),
)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("pairs")
    for seed in range(3):
        save_frame_pair(make_pair(num_views=3, height=32, width=48, seed=seed), folder / f"pair_{seed:06d}.npz")
    return folder


def _config(data_dir: Path, out: Path, **kw) -> TrainConfig:
    base = dict(
        data=str(data_dir),
        out=str(out),
        steps=4,
        ckpt_every=2,
        log_every=1,
        val_every=1000,
        lpips="stlpips",
        model=TINY_MODEL,
        threads=1,
    )
    base.update(kw)
    return TrainConfig(**base)


@pytest.mark.parametrize("stage", ["static", "dynamic", "joint"])
def test_each_stage_trains_and_exports(data_dir, tmp_path, stage):
    path = train(_config(data_dir, tmp_path / stage, stage=stage), show_progress=False)
    assert path.exists() and path.with_suffix(".json").exists()
    records = [json.loads(line) for line in (tmp_path / stage / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3, 4]
    expected = {"static": {"loc", "smooth"}, "dynamic": {"warp", "consist"}, "joint": {"loc", "warp"}}[stage]
    assert expected <= set(records[0]) and all(torch.isfinite(torch.tensor(r["loss"])) for r in records)


def _assert_trained_only(before: dict, after: dict, trained: str, frozen: tuple[str, ...]) -> None:
    """The parameters under ``frozen`` prefixes are bit-identical (batch-norm statistics aside) and
    some under ``trained`` changed."""
    for key, value in before.items():
        if key.startswith(frozen) and "running" not in key and "num_batches" not in key:
            torch.testing.assert_close(after[key], value, rtol=0, atol=0, msg=key)
    assert any(not torch.equal(after[k], before[k]) for k in after if k.startswith(trained)), f"{trained} did not train"


def test_dynamic_stage_leaves_depth_and_gaussian_head_untouched(data_dir, tmp_path):
    static = train(_config(data_dir, tmp_path / "s", stage="static", steps=2), show_progress=False)
    dynamic = train(_config(data_dir, tmp_path / "d", stage="dynamic", steps=2, init=str(static)), show_progress=False)
    _assert_trained_only(load_file(str(static)), load_file(str(dynamic)), "flow_net.", ("depth_net.", "gaussian_head."))


def test_init_with_a_reshaped_flow_network_keeps_depth_and_leaves_new_shapes_fresh(data_dir, tmp_path, caplog):
    static = train(_config(data_dir, tmp_path / "s", stage="static", steps=1), show_progress=False)
    wider = replace(TINY_MODEL, flow=replace(TINY_MODEL.flow, coarse_radius=5))
    config = _config(data_dir, tmp_path / "d", stage="dynamic", steps=1, init=str(static), model=wider)
    dynamic = train(config, show_progress=False)
    before, after = load_file(str(static)), load_file(str(dynamic))
    depth = [k for k in before if k.startswith("depth_net.") and "running" not in k and "num_batches" not in k]
    assert depth and all(torch.equal(after[k], before[k]) for k in depth)
    reshaped = [k for k in after if k in before and after[k].shape != before[k].shape]
    assert reshaped and all(".levels.3.body.0." in k for k in reshaped)
    assert "left at initialisation" in caplog.text


def test_resume_after_interruption_matches_an_uninterrupted_run(data_dir, tmp_path):
    full = train(_config(data_dir, tmp_path / "full", steps=4), show_progress=False)
    train(_config(data_dir, tmp_path / "cut", steps=2), show_progress=False)
    resumed = train(_config(data_dir, tmp_path / "cut", steps=4), resume=True, show_progress=False)
    a, b = load_file(str(full)), load_file(str(resumed))
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=1e-5, atol=1e-6, msg=key)


def test_resume_drops_log_records_after_the_checkpoint(data_dir, tmp_path):
    out = tmp_path / "run"
    train(_config(data_dir, out, steps=2), show_progress=False)
    with open(out / "log.jsonl", "a") as f:  # a killed run logged step 3 but never checkpointed it
        f.write(json.dumps({"step": 3, "loss": 9.0, "seconds": 1.0}) + "\n")
    train(_config(data_dir, out, steps=4), resume=True, show_progress=False)
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3, 4] and records[2]["loss"] != 9.0


def test_refuses_to_overwrite_or_resume_nothing(data_dir, tmp_path):
    from drivingscene.errors import InputError

    train(_config(data_dir, tmp_path / "r", steps=1), show_progress=False)
    with pytest.raises(InputError, match="already there"):
        train(_config(data_dir, tmp_path / "r", steps=1), show_progress=False)
    with pytest.raises(InputError, match="no checkpoint"):
        train(_config(data_dir, tmp_path / "empty", steps=1), resume=True, show_progress=False)


def test_a_second_trainer_on_a_run_folder_is_refused_naming_the_first(data_dir, tmp_path):
    from drivingscene.errors import InputError
    from drivingscene.train.trainer import run_lock

    out = tmp_path / "run"
    train(_config(data_dir, out, steps=1), show_progress=False)
    with run_lock(out):  # another trainer writing the folder
        for resume in (True, False):
            with pytest.raises(InputError, match=rf"another trainer \(pid {os.getpid()}\) is writing this run folder"):
                train(_config(data_dir, out, steps=2), resume=resume, show_progress=False)
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1]  # nothing written twice
    train(_config(data_dir, out, steps=2), resume=True, show_progress=False)  # free again once it ends


def test_a_second_trainer_exits_2_with_one_line(data_dir, tmp_path):
    from drivingscene.train.trainer import run_lock

    out = tmp_path / "run"
    config = tmp_path / "config.json"
    config.write_text(_config(data_dir, out, steps=1).to_json())
    args = [sys.executable, "-m", "drivingscene", "train", "--stage", "static", "--config", str(config)]
    args += ["--data", str(data_dir), "--out", str(out), "--no-progress", "--resume"]
    with run_lock(out):
        proc = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        f"drivingscene train: error: {out}: another trainer (pid {os.getpid()}) is writing this run folder; "
        "let it finish or stop it, then --resume"
    ]


def test_torchrun_two_processes(data_dir, tmp_path):
    """DistributedDataParallel over gloo: 2 processes, 2 steps, one exported model."""
    config = tmp_path / "config.json"
    config.write_text(_config(data_dir, tmp_path / "ddp", steps=2).to_json())
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc-per-node",
        "2",
        "--master-port",
        "29517",
        "-m",
        "drivingscene",
        "train",
        "--stage",
        "static",
        "--config",
        str(config),
        "--data",
        str(data_dir),
        "--out",
        str(tmp_path / "ddp"),
        "--no-progress",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    meta = json.loads((tmp_path / "ddp" / "model.json").read_text())
    assert meta["world"] == 2 and meta["steps"] == 2


def test_ship_weights_from_a_run_in_float16(data_dir, tmp_path, capsys):
    from drivingscene.cli import main
    from drivingscene.methods.feedforward import load_model

    run = tmp_path / "run"
    train(_config(data_dir, run, steps=2), show_progress=False)
    assert main(["ship-weights", str(run), str(tmp_path / "w.safetensors")]) == 0
    shipped = load_file(str(tmp_path / "w.safetensors"))
    assert all(v.dtype == torch.float16 for v in shipped.values() if v.is_floating_point())
    meta = json.loads((tmp_path / "w.json").read_text())
    assert meta["dtype"] == "float16" and meta["steps"] == 2 and meta["model"]["input_size"] == [32, 48]
    full = load_model(run / "model.safetensors")
    half = load_model(tmp_path / "w.safetensors")
    for (name, a), b in zip(full.state_dict().items(), half.state_dict().values()):
        if a.is_floating_point():
            torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-4, msg=name)
    assert main(["ship-weights", str(run), str(tmp_path / "w.safetensors")]) == 2  # never overwrites
    assert "exists" in capsys.readouterr().err


def test_training_report_wall_time_survives_a_kill_and_resume():
    from drivingscene.bench.training_report import wall_hours

    # Old records without timestamps (2 s steps, logged every 10), a kill, a resume that repeats
    # steps 20-30 with timestamps 1.5 s apart per step, and an hour-long pause that is not training.
    recs = [{"step": s, "seconds": 2.0} for s in (10, 20, 30)]
    recs += [{"step": s, "seconds": 1.5, "time": 1000.0 + 1.5 * (s - 20)} for s in (20, 30, 40)]
    recs += [{"step": 50, "seconds": 1.5, "time": 1000.0 + 30 + 3600}]
    # 0-10: 10 x 2 s (old run); 10-20: retrained by the resumed run, 10 x 1.5 s (its step-20
    # record replaces the old one); 20-40: 30 s of timestamps; 40-50: the pause counts as 10 x 1.5 s.
    assert wall_hours(recs) * 3600 == pytest.approx(20 + 15 + 30 + 15)


def test_flow_lr_applies_to_the_residual_flow_network_only():
    from drivingscene.models.model import DrivingSceneModel
    from drivingscene.train.trainer import _param_groups, _trainable

    model = DrivingSceneModel(TINY_MODEL)
    config = TrainConfig(stage="joint", flow_lr=5e-4, lr=1e-4)
    groups = _param_groups(model, _trainable(model, "joint"), config)
    flow = {id(p) for p in model.flow_net.parameters()}
    assert [g["lr"] for g in groups] == [1e-4, 5e-4]
    assert {id(p) for p in groups[1]["params"]} == flow
    assert not flow & {id(p) for p in groups[0]["params"]}
    static = _param_groups(model, _trainable(model, "static"), config)  # R frozen: one group, lr
    assert [g["lr"] for g in static] == [1e-4] and len(static[0]["params"]) == len(_trainable(model, "static"))
    assert [g["lr"] for g in _param_groups(model, _trainable(model, "dynamic"), TrainConfig(stage="dynamic"))] == [1e-4]


def test_training_report_from_runs(data_dir, tmp_path):
    from drivingscene.cli import main

    static = tmp_path / "static"
    train(_config(data_dir, static, stage="static", steps=2), show_progress=False)
    train(_config(data_dir, static, stage="static", steps=3), resume=True, show_progress=False)
    dynamic = tmp_path / "dynamic"
    train(_config(data_dir, dynamic, stage="dynamic", steps=2, flow_lr=5e-4), show_progress=False)
    sessions = [json.loads(line) for line in (static / "sessions.jsonl").read_text().splitlines()]
    assert [s["start_step"] for s in sessions] == [0, 2] and sessions[0]["threads"] == 1
    figure, out = tmp_path / "curves.png", tmp_path / "training.md"
    args = ["bench", "training", str(static), str(dynamic), "--figure", str(figure), "--out", str(out)]
    assert main(args) == 0
    text = out.read_text()
    assert "| static | static | 3 | 0.0001 | frozen | 0.0 | – | – | scratch |" in text
    assert "| dynamic | dynamic | 2 | frozen | 0.0005 | – | 0.0 | 0.0 |" in text
    assert "1 process(es) x 1 thread(s)" in text
    assert figure.stat().st_size > 1000


def test_flow_supervision_term_and_resume_keeps_the_runs_settings(data_dir, tmp_path, capsys):
    from drivingscene.cli import main

    out = tmp_path / "sup"
    args = ["train", "--stage", "dynamic", "--data", str(data_dir), "--out", str(out), "--steps", "2", "--threads", "1"]
    args += ["--lpips", "stlpips", "--ckpt-every", "2", "--no-progress"]
    tiny = tmp_path / "tiny.json"
    tiny.write_text(json.dumps(TrainConfig(model=TINY_MODEL, log_every=1).to_dict()))
    extra = ["--flow-supervision", "0.1", "--search-supervision", "0.05", "--flow-lr", "5e-4"]
    assert main([*args, "--config", str(tiny), *extra]) == 0
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert all(r["flow_sup"] > 0 and r["search_sup"] >= 0 and 0 <= r["search_px"] <= 1 for r in records)
    # --resume with no settings continues with the run's own (supervision, R's learning rate)
    assert (
        main(
            [
                "train",
                "--stage",
                "dynamic",
                "--data",
                str(data_dir),
                "--out",
                str(out),
                "--steps",
                "3",
                "--resume",
                "--no-progress",
            ]
        )
        == 0
    )
    saved = json.loads((out / "config.json").read_text())
    assert saved["weights"]["flow_sup"] == 0.1 and saved["weights"]["search_sup"] == 0.05
    assert saved["flow_lr"] == 5e-4 and saved["steps"] == 3
    assert "flow_sup" in json.loads((out / "log.jsonl").read_text().splitlines()[-1])
    assert main([*args[:-1], "--out", str(tmp_path / "neg"), "--flow-supervision", "-1"]) == 2
    assert "--flow-supervision: expected a weight >= 0" in capsys.readouterr().err
    assert main([*args[:-1], "--out", str(tmp_path / "neg"), "--search-supervision", "-1"]) == 2
    assert "--search-supervision: expected a weight >= 0" in capsys.readouterr().err


def test_depth_supervision_term_in_stage_one(data_dir, tmp_path):
    from drivingscene.cli import main

    tiny = tmp_path / "tiny.json"
    tiny.write_text(json.dumps(TrainConfig(model=TINY_MODEL, log_every=1).to_dict()))
    out = tmp_path / "depth"
    args = ["train", "--stage", "static", "--data", str(data_dir), "--out", str(out), "--steps", "2", "--threads", "1"]
    assert main([*args, "--config", str(tiny), "--lpips", "stlpips", "--depth-supervision", "0.5", "--no-progress"]) == 0
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert all(r["depth_sup"] > 0 for r in records)
    assert json.loads((out / "config.json").read_text())["weights"]["depth_sup"] == 0.5


def test_the_validation_best_weights_are_kept(data_dir, tmp_path, monkeypatch):
    """best.safetensors holds the weights of the best validation so far (rolling checkpoints keep the
    last two only); a worse later validation does not replace them, a better one does."""
    from drivingscene.train import trainer

    scores = iter([18.0, 19.5, 19.0, 20.0])
    monkeypatch.setattr(trainer, "validate", lambda model, files, config: {"psnr": next(scores), "depth_abs_rel": 0.1})
    out = tmp_path / "run"
    config = _config(data_dir, out, stage="static", steps=3, val_every=1, val_data=str(data_dir))
    train(config, show_progress=False)
    kept = json.loads((out / "best.json").read_text())
    assert kept["steps"] == 2 and kept["val"]["psnr"] == 19.5
    best = load_file(str(out / "best.safetensors"))
    final = load_file(str(out / "model.safetensors"))
    assert best.keys() == final.keys() and any(not torch.equal(best[k], final[k]) for k in best)
    train(replace(config, steps=4), resume=True, show_progress=False)  # resumed: a better score replaces it
    assert json.loads((out / "best.json").read_text())["steps"] == 4


def test_gaussian_stage_trains_the_gaussian_head_alone(data_dir, tmp_path):
    static = train(_config(data_dir, tmp_path / "s", stage="static", steps=2), show_progress=False)
    tuned = train(_config(data_dir, tmp_path / "g", stage="gaussians", steps=3, init=str(static)), show_progress=False)
    _assert_trained_only(load_file(str(static)), load_file(str(tuned)), "gaussian_head.", ("depth_net.", "flow_net."))
    records = [json.loads(line) for line in (tmp_path / "g" / "log.jsonl").read_text().splitlines()]
    assert all(set(r) >= {"render"} and "loc" not in r for r in records)


def test_depth_stage_trains_the_depth_network_alone_and_keeps_its_best_depth(data_dir, tmp_path, monkeypatch):
    from drivingscene.train import trainer

    static = train(_config(data_dir, tmp_path / "s", stage="static", steps=2), show_progress=False)
    scores = iter([0.30, 0.20, 0.25])  # depth AbsRel: lower is better, so step 1 is kept
    monkeypatch.setattr(trainer, "validate", lambda model, files, config: {"psnr": 20.0, "depth_abs_rel": next(scores)})
    out = tmp_path / "d"
    config = _config(data_dir, out, stage="depth", steps=2, val_every=1, val_data=str(data_dir), init=str(static))
    tuned = train(replace(config, weights=replace(config.weights, depth_sup=0.1)), show_progress=False)
    _assert_trained_only(load_file(str(static)), load_file(str(tuned)), "depth_net.", ("gaussian_head.", "flow_net."))
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert all({"loc", "smooth", "depth_sup"} <= set(r) and "warp" not in r for r in records if "loss" in r)
    assert json.loads((out / "best.json").read_text())["steps"] == 1


def test_render_targets_come_in_turn(data_dir, monkeypatch):
    """eval, cross, input, eval, ...: the cross view renders one keyframe's Gaussians ("all"), the
    input view both keyframes' in the configured blend at the keyframe's own time."""
    import drivingscene.train.stages as stages
    from drivingscene.data import load_frame_pair
    from drivingscene.data.tensors import pair_to_tensors
    from drivingscene.models.model import DrivingSceneModel
    from drivingscene.models.pipeline import predict_static

    calls = []

    def spy(gaussians, t, *args, blend="all", **kwargs):
        calls.append((sorted(set(gaussians.keyframes.tolist())), float(t), blend))
        return real(gaussians, t, *args, blend=blend, **kwargs)

    real = stages.render_gaussians
    monkeypatch.setattr(stages, "render_gaussians", spy)
    pair = load_frame_pair(sorted(data_dir.glob("*.npz"))[0])
    assert pair.num_eval, "the factory pair should have an intermediate frame"
    batch = pair_to_tensors(pair)
    model = DrivingSceneModel(TINY_MODEL).eval()
    step = stages.TrainStep(model, TrainConfig(model=TINY_MODEL, amp=False), None)
    with torch.no_grad():
        static = predict_static(model, batch)
        for i in range(6):
            assert torch.isfinite(step.render_term(static, batch, i, scene_flow=None))
    t_eval = float(batch.eval_times[0])
    assert calls[0] == ([0, 1], t_eval, "layers")
    assert calls[1] == ([1], 0.0, "all") and calls[4] == ([0], 1.0, "all")  # keyframe k from the other's
    assert calls[2] == ([0, 1], 0.0, "layers") and calls[5] == ([0, 1], 1.0, "layers")


def test_runs_saved_before_render_views_keep_their_targets():
    legacy = TrainConfig.from_dict({"stage": "static"})
    assert legacy.render_views == ("eval", "cross") and legacy.render_blend == "all"
    assert TrainConfig().render_views == ("eval", "cross", "input") and TrainConfig().render_blend == "layers"
    again = TrainConfig.from_dict(json.loads(TrainConfig().to_json()))
    assert again.render_views == ("eval", "cross", "input")
    with pytest.raises(ValueError, match="render_views"):
        TrainConfig(render_views=("side",))


def test_a_run_from_init_validates_its_starting_weights_first(data_dir, tmp_path, monkeypatch):
    """Step 0 of a run with --init and validation data: the starting weights' scores, which are
    also the best so far until a step beats them."""
    from drivingscene.train import trainer

    static = train(_config(data_dir, tmp_path / "s", stage="static", steps=1), show_progress=False)
    scores = iter([21.0, 20.0, 20.5])
    monkeypatch.setattr(trainer, "validate", lambda model, files, config: {"psnr": next(scores)})
    out = tmp_path / "g"
    train(
        _config(data_dir, out, stage="gaussians", steps=2, val_every=1, val_data=str(data_dir), init=str(static)),
        show_progress=False,
    )
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert records[0]["step"] == 0 and records[0]["val"]["psnr"] == 21.0 and "loss" not in records[0]
    assert [r["step"] for r in records[1:]] == [1, 2]
    assert json.loads((out / "best.json").read_text())["steps"] == 0
    best, start = load_file(str(out / "best.safetensors")), load_file(str(static))
    assert all(torch.equal(best[k], start[k]) for k in start)
