"""Several training seeds through the harness executors give the same results as one by one."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import torch

from benchmark.cli import main


def _tensors(obj: object, prefix: str = "") -> dict[str, torch.Tensor]:
    """All tensors of a (nested) checkpoint, by path (metadata such as timings left out)."""
    out: dict[str, torch.Tensor] = {}
    if isinstance(obj, torch.Tensor):
        out[prefix] = obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_tensors(v, f"{prefix}/{k}"))
    elif isinstance(obj, list | tuple):
        for i, v in enumerate(obj):
            out.update(_tensors(v, f"{prefix}/{i}"))
    return out


def test_seeds_on_process_executor_equal_serial(tmp_path: Path) -> None:
    common = ["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--vehicles", "3",
              "--steps", "1500"]
    assert main([*common, "--seeds", "0,1", "--executor", "process", "--workers", "2",
                 "--out", str(tmp_path / "p")]) == 0
    assert main([*common, "--seed", "1", "--out", str(tmp_path / "s")]) == 0
    stem = "ia2c__catchup-v1__n3__s1"
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "p" / f"{stem}.curve.csv"),
                                  pd.read_csv(tmp_path / "s" / f"{stem}.curve.csv"))
    a = torch.load(tmp_path / "p" / f"{stem}.pt", weights_only=True)
    b = torch.load(tmp_path / "s" / f"{stem}.pt", weights_only=True)
    wa, wb = _tensors(a), _tensors(b)
    assert wa.keys() == wb.keys() and wa
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    assert (tmp_path / "p" / "ia2c__catchup-v1__n3__s0.pt").exists()


def test_bad_seeds_exit_2(tmp_path: Path) -> None:
    assert main(["train", "--algo", "ia2c", "--scenario", "catchup-v1", "--seeds", "a,b",
                 "--out", str(tmp_path)]) == 2
    assert main(["train", "--algo", "nope", "--scenario", "catchup-v1",
                 "--out", str(tmp_path)]) == 2


def test_set_config_fields(tmp_path: Path, capsys) -> None:
    """``--set KEY=VALUE`` reaches the checkpoint's config, typed; bad pairs exit 2 with a
    message naming the key, before anything is trained."""
    assert main(["train", "--algo", "bdc", "--scenario", "catchup-v1", "--vehicles", "3",
                 "--steps", "700", "--out", str(tmp_path), "--set", "gamma=0.995",
                 "--set", "advantage_norm=true", "--set", "qsgd_bucket=none"]) == 0
    cfg = torch.load(tmp_path / "bdc__catchup-v1__n3__s0.pt", weights_only=True)["config"]
    assert cfg["gamma"] == 0.995 and cfg["advantage_norm"] is True and cfg["qsgd_bucket"] is None
    capsys.readouterr()
    for bad in ("nope=1", "gamma", "gamma=high", "advantage_norm=maybe", "gamma=2"):
        assert main(["train", "--algo", "bdc", "--scenario", "catchup-v1", "--set", bad,
                     "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert bad.split("=")[0] in err and "Traceback" not in err, bad
    assert not (tmp_path / "bad").exists()
