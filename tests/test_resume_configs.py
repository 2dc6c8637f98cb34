"""A run resumed in its own folder keeps each earlier segment's ``.hydra`` records (``config.<k>.yaml``,
``overrides.<k>.yaml``, ``hydra.<k>.yaml``) before Hydra rewrites them; a refused resume keeps none."""
from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from cicfw.core.run_folder import keep_segment_records

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)


def dropout(path: Path) -> object:
    return OmegaConf.load(path).encoder.dropout_fc


def test_each_resume_keeps_the_earlier_segments_config(tmp_path: Path) -> None:
    from conftest import run_app_in_process, write_tiny_dataset

    data = write_tiny_dataset(tmp_path / "data")
    run = tmp_path / "run"
    hydra = run / ".hydra"
    args = ["data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false",
            "trainer.limit_train_batches=1", "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0",
            "trainer.enable_model_summary=false", "speed.compile=false", f"hydra.run.dir={run}"]
    first = run_app_in_process("cicfw.train", *args, "trainer.max_epochs=1", "encoder.dropout_fc=0.1")
    assert first.returncode == 0, first.stderr[-2000:]
    records = {p.name: p.read_bytes() for p in hydra.iterdir()}
    assert sorted(records) == ["config.yaml", "hydra.yaml", "overrides.yaml"]

    refused = run_app_in_process("cicfw.train", *args, "trainer.max_epochs=2", "data.seed=7", "ckpt_path=last")
    assert refused.returncode == 2 and "data.seed" in refused.stderr, refused.stderr[-2000:]
    assert {p.name: p.read_bytes() for p in hydra.iterdir()} == records  # nothing kept, nothing rewritten

    again = run_app_in_process("cicfw.train", *args, "trainer.max_epochs=2", "encoder.dropout_fc=0.5", "ckpt_path=last")
    assert again.returncode == 0, again.stderr[-2000:]
    assert {n: (hydra / n).read_bytes() for n in ("config.1.yaml", "hydra.1.yaml", "overrides.1.yaml")} == {
        "config.1.yaml": records["config.yaml"], "hydra.1.yaml": records["hydra.yaml"],
        "overrides.1.yaml": records["overrides.yaml"]}
    assert (dropout(hydra / "config.1.yaml"), dropout(hydra / "config.yaml")) == (0.1, 0.5)
    assert "encoder.dropout_fc=0.5" in OmegaConf.load(hydra / "overrides.yaml")
    assert (run / "csv" / "metrics.1.csv").is_file()  # the metrics' numbering: the first resume keeps .1
    kept = {p.name: p.read_bytes() for p in hydra.glob("*.1.yaml")}

    # a checkpoint written before checkpoints recorded their data split: its resume is checked against the
    # config its own segment trained with (kept as config.2.yaml while it checks), not against config.yaml,
    # which Hydra has just rewritten with this very command (data.seed=7 compared with itself would pass)
    import torch

    from cicfw.model.checkpoint import SPLIT_KEY

    last = run / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, weights_only=False)
    assert ckpt.pop(SPLIT_KEY, None) is not None
    torch.save(ckpt, last)
    legacy = run_app_in_process("cicfw.train", *args, "trainer.max_epochs=3", "encoder.dropout_fc=0.3", "data.seed=7",
                                "ckpt_path=last")
    assert legacy.returncode == 2 and "data.seed=7" in legacy.stderr, legacy.stderr[-2000:]
    assert {p.name: p.read_bytes() for p in hydra.glob("*.1.yaml")} == kept and not list(hydra.glob("*.2.yaml"))


def test_a_kept_record_is_never_replaced(tmp_path: Path) -> None:
    hydra = tmp_path / ".hydra"
    hydra.mkdir()
    (hydra / "config.yaml").write_text("a: 3\n")
    (hydra / "overrides.1.yaml").write_text("- kept\n")  # a number taken by any record is taken for all
    assert keep_segment_records(tmp_path) == 2
    assert (hydra / "overrides.1.yaml").read_text() == "- kept\n" and (hydra / "config.2.yaml").read_text() == "a: 3\n"
    assert sorted(p.name for p in hydra.iterdir()) == ["config.2.yaml", "config.yaml", "overrides.1.yaml"]
    assert keep_segment_records(tmp_path / "nothing") is None
