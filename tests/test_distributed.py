"""``ns-train geometrysticker`` over two processes: the host's distributed path, driven on the CPU over gloo.

Nerfstudio's launcher (``--machine.num-devices 2``) asserts CUDA before it starts its workers; this test does what each
of its workers does after those checks: ``dist.init_process_group`` (gloo here, NCCL on GPUs), then nerfstudio's
``train_loop``, ``comms.synchronize`` and ``dist.destroy_process_group``. The config is parsed by ns-train's own tyro
union and saved as ``ns-train`` saves it. This file is also the workers' script (``python test_distributed.py RANK
...``): each rank leaves its message and trained state in a file, and the test compares the two ranks.
"""

from __future__ import annotations

import pickle
import socket
import subprocess
import sys
import time
from datetime import timedelta
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from conftest import CPU_ARGS, TINY_STICKER_ARGS, subprocess_env

WORLD_SIZE = 2


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def run_rank(rank: int, world_size: int, port: int, config_file: Path, out_dir: Path) -> None:
    """One rank as nerfstudio's ``_distributed_worker`` runs it past its CUDA checks (gloo); then the rank's message
    and trained state (all but the frozen base) go to ``out_dir/rank{rank}.pt``."""
    from nerfstudio.scripts.train import train_loop
    from nerfstudio.utils import comms
    from torch.nn.parallel import DistributedDataParallel

    from gsticker_plugin.trainer import GeometryStickerTrainer

    config = pickle.loads(config_file.read_bytes())
    trainers = []
    train = GeometryStickerTrainer.train

    def train_and_keep(self) -> None:
        train(self)
        trainers.append(self)

    GeometryStickerTrainer.train = train_and_keep  # this worker's own copy of the class: keep the trained trainer
    dist.init_process_group(
        "gloo",
        init_method=f"tcp://127.0.0.1:{port}",
        world_size=world_size,
        rank=rank,
        timeout=timedelta(minutes=5),
    )
    comms.LOCAL_PROCESS_GROUP = dist.new_group(list(range(world_size)))
    train_loop(local_rank=rank, world_size=world_size, config=config, global_rank=rank)
    comms.synchronize()
    trainer = trainers[0]
    pipe = trainer.pipeline
    torch.save(
        {
            "message": pipe.owner_message.clone(),
            "batch_seed": pipe.generator.initial_seed(),
            "step": trainer.step,
            "world_size": pipe.world_size,
            "ddp": isinstance(pipe._model, DistributedDataParallel),
            "model": {k: v.clone() for k, v in pipe.model.state_dict().items() if not k.startswith("base.")},
            "heads": {k: v.clone() for k, v in pipe.heads.state_dict().items()},
        },
        out_dir / f"rank{rank}.pt",
    )
    dist.destroy_process_group()


@pytest.mark.slow
def test_two_gloo_ranks_write_one_run_and_one_key_that_verifies(tiny_base, tmp_path):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from gsticker_plugin.key import OwnerKey, default_key_path
    from gsticker_plugin.verify.cli import main as verify_main

    t0 = time.time()
    ws, keys, ranks = tmp_path / "ws", tmp_path / "keys", tmp_path / "ranks"
    ranks.mkdir()
    key = keys / "owner.gskey"
    ckpt = max((tiny_base.parent / "nerfstudio_models").glob("step-*.ckpt"))
    # ns-train's main(): parse, timestamp, save the config; then what each worker of its launcher does
    config = tyro.cli(
        AnnotatedBaseConfigUnion,
        args=[
            "geometrysticker",
            "--load-checkpoint",
            str(ckpt),
            *CPU_ARGS,
            "--machine.num-devices",
            str(WORLD_SIZE),
            "--output-dir",
            str(ws),
            "--experiment-name",
            "gs",
            "--timestamp",
            "ddp",
            *TINY_STICKER_ARGS,
            "--pipeline.key-path",
            str(key),
        ],
    )
    config.set_timestamp()
    config.save_config()
    config_file = tmp_path / "config.pkl"
    config_file.write_bytes(pickle.dumps(config))
    port = free_port()
    procs = []
    for rank in range(WORLD_SIZE):
        cmd = [sys.executable, __file__, str(rank), str(WORLD_SIZE), str(port), str(config_file), str(ranks)]
        log = open(tmp_path / f"rank{rank}.log", "w+")
        procs.append((subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=subprocess_env(1)), log))
    deadline = time.time() + 300
    codes = []
    for proc, log in procs:
        try:
            codes.append(proc.wait(timeout=max(1.0, deadline - time.time())))
        except subprocess.TimeoutExpired:
            proc.kill()
            codes.append(proc.wait())
        log.seek(0)
        tail = log.read()[-3000:]
        log.close()
        assert codes[-1] == 0, f"rank {len(codes) - 1} exited {codes[-1]}:\n{tail}"
    print(f"2 ranks trained in {time.time() - t0:.1f} s")

    # one run folder, one checkpoint, one key; config.yml as rank 0 rewrote it (no key path)
    run_dirs = list((ws / "gs" / "geometrysticker").iterdir())
    assert [d.name for d in run_dirs] == ["ddp"]
    run = run_dirs[0]
    assert (run / "config.yml").is_file()
    assert str(key) not in (run / "config.yml").read_text()
    assert [p.name for p in (run / "nerfstudio_models").iterdir()] == ["step-000000009.ckpt"]
    assert [p.name for p in keys.iterdir()] == ["owner.gskey"]
    assert not default_key_path("gs", "geometrysticker", "ddp").exists()
    assert not list(ws.rglob("*.gskey")) and not list(ws.rglob("*.tmp"))

    # both ranks: rank 0's message, distinct batches, identical trained state (broadcast start, averaged gradients)
    r0, r1 = (torch.load(ranks / f"rank{r}.pt", weights_only=False) for r in range(WORLD_SIZE))
    owner = OwnerKey.load(key)
    assert owner.message_source == "random"
    assert torch.equal(owner.message, r0["message"]) and torch.equal(owner.message, r1["message"])
    assert r0["batch_seed"] != r1["batch_seed"]
    assert r0["step"] == r1["step"] == 9 and owner.training_state["step"] == 9
    assert r0["world_size"] == r1["world_size"] == WORLD_SIZE and not r0["ddp"] and not r1["ddp"]
    for part in ("model", "heads"):
        assert r0[part].keys() == r1[part].keys()
        differ = [k for k in r0[part] if not torch.equal(r0[part][k], r1[part][k])]
        assert not differ, f"{part} differs between the ranks: {differ}"
    assert all(torch.equal(owner.heads_state[k], v) for k, v in r0["heads"].items())

    status = verify_main(
        ["--load-config", str(run / "config.yml"), "--key", str(key), "--output", str(tmp_path / "verify")]
        + ["--num-views", "4", "--no-progress"]
    )
    assert status == 0
    print(f"test total {time.time() - t0:.1f} s")


if __name__ == "__main__":
    rank_, world_size_, port_, config_file_, out_dir_ = sys.argv[1:6]
    run_rank(int(rank_), int(world_size_), int(port_), Path(config_file_), Path(out_dir_))
