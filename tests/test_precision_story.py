"""One precision story: every training recipe is fp32 (`32-true`, TF32 off) until a driving license study
says otherwise. bf16 autocast was tested and not licensed (docs/results/bf16_license_xeon/), so no config
and no documented command asks for a lower precision except the license study itself (the catalogue row
`cil_bf16`); the GPU check trains in fp32 and prints the commands of that study on a GPU."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import torch

from conftest import compose_train, load_bench_script

ROOT = Path(__file__).resolve().parents[1]
#: a Lightning precision other than fp32/fp64, after `precision=` or `precision:` (bf16-mixed, 16-mixed, bf16, 16-true, ...)
REDUCED = re.compile(r"precision\s*[:=]\s*[\"']?((?:bf)?16[\w-]*|transformer-engine[\w-]*)")
#: the license study's row: the one place a reduced precision is asked for
LICENSE_ROW = "cil_bf16"
COMMAND_START = ("python ", "cicfw ", "srun ", "sbatch ", "torchrun ")


def conf_offences(root: Path) -> list[str]:
    """``file:line`` of every conf/ line (comments included) that asks for a reduced precision outside the
    license study's catalogue row."""
    out = []
    for f in sorted((root / "conf").rglob("*.yaml")):
        for n, text in enumerate(f.read_text().splitlines(), 1):
            if REDUCED.search(text) and LICENSE_ROW not in text:
                out.append(f"{f.relative_to(root)}:{n}: {text.strip()}")
    return out


def doc_recipes(text: str) -> list[tuple[int, str]]:
    """The commands a Markdown document gives, with their line numbers: every line of a fenced code
    block (a backslash-continued command joined into one) and every inline code span that starts a
    command (``python ...``, ``cicfw ...``)."""
    out: list[tuple[int, str]] = []
    fenced, pending, start = False, "", 0
    for n, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced, pending = not fenced, ""
            continue
        if fenced:
            if not pending:
                start = n
            pending += line.rstrip().rstrip("\\") + " "
            if not line.rstrip().endswith("\\"):
                out.append((start, pending.strip()))
                pending = ""
            continue
        for span in re.findall(r"`([^`]+)`", line):
            if span.startswith(COMMAND_START):
                out.append((n, span))
    return out


def doc_offences(root: Path) -> list[str]:
    """``file:line`` of every documented command (README.md, docs/*.md; the results folders are records of
    studies run, not recipes) that asks for a reduced precision outside the license study."""
    out = []
    for f in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        if not f.is_file():
            continue
        for n, cmd in doc_recipes(f.read_text()):
            if REDUCED.search(cmd) and LICENSE_ROW not in cmd:
                out.append(f"{f.relative_to(root)}:{n}: {cmd}")
    return out


def test_trainer_ddp_composes_to_fp32():
    assert compose_train("trainer=ddp").trainer.precision == "32-true"
    assert compose_train().trainer.precision == "32-true"


def test_no_config_or_documented_recipe_asks_for_a_reduced_precision_outside_the_license_study():
    assert conf_offences(ROOT) == []
    assert doc_offences(ROOT) == []
    # the license study's row is where bf16 lives, and it still does
    assert any(LICENSE_ROW in line and REDUCED.search(line) for line in (ROOT / "conf" / "reproduce.yaml").read_text().splitlines())


def test_the_scan_finds_what_it_must(tmp_path):
    """The rules above fail on the recipes this project used to ship (checked on copies)."""
    (tmp_path / "conf" / "trainer").mkdir(parents=True)
    (tmp_path / "docs").mkdir()
    (tmp_path / "conf" / "trainer" / "ddp.yaml").write_text(
        "#   4 GPUs:  python -m cicfw.train trainer=ddp trainer.precision=16-mixed\nprecision: bf16-mixed   # autocast\n")
    (tmp_path / "conf" / "reproduce.yaml").write_text(
        'cil_bf16: {experiment: paper_cil, overrides: ["trainer.precision=bf16-mixed"]}\n')
    (tmp_path / "docs" / "scaling.md").write_text(
        "Run\n\n```bash\npython -m cicfw.train trainer.accelerator=gpu \\\n    trainer.precision=bf16-mixed data.num_workers=4\n"
        "python -m cicfw.reproduce 'rows=[cil_bf16]' seeds=[0]\n```\n\nor `python -m cicfw.train trainer.precision=16-mixed`;"
        " the row sets `trainer.precision=bf16-mixed` (prose, not a command).\n")
    assert [o.split(":")[:2] for o in conf_offences(tmp_path)] == [["conf/trainer/ddp.yaml", "1"], ["conf/trainer/ddp.yaml", "2"]]
    assert [o.split(":")[:2] for o in doc_offences(tmp_path)] == [["docs/scaling.md", "4"], ["docs/scaling.md", "9"]]


def test_gpu_check_trains_in_fp32_and_prints_the_license_study(capsys):
    m = load_bench_script("gpu_check")
    assert "trainer.precision=32-true" in m.GPU_RECIPE and not any(REDUCED.search(o) for o in m.GPU_RECIPE)
    assert m.main(["--license-study"]) == 0
    out = capsys.readouterr().out
    commands = [line.strip() for line in out.splitlines() if line.strip().startswith("python -m cicfw.reproduce ")]
    assert len(commands) == len(m.LICENSE_SEEDS) == 8
    first = []
    for seed, cmd in zip(m.LICENSE_SEEDS, commands):
        args = dict(a.split("=", 1) for a in shlex.split(cmd)[3:])
        assert args["budget"] == "converged6" and args["seeds"] == f"[{seed}]"
        assert set(args["rows"].strip("[]").split(",")) == {"cil", "cil_bf16"}
        first.append(args["rows"].strip("[]").split(",")[0])
        train = args["budget.train"]
        assert all(o in train for o in (*m.budget_train("converged6"), "trainer.accelerator=gpu"))
        assert "precision" not in train  # the precision comes from the row alone
    assert first == ["cil", "cil_bf16"] * 4  # the order alternates within a pair
    test = next(line.strip() for line in out.splitlines() if "cicfw.reproduction.paired_switch" in line)
    parts = test.split()
    assert parts[-4].endswith("/cells/cil_bf16") and parts[-3].endswith("/cells/cil") and parts[-2:] == ["--margin", "5"]
    assert "equivalent within ±5" in out and "before its first cell" in out


@pytest.mark.slow
def test_the_printed_study_commands_pass_the_reproduce_apps_own_checks(capsys):
    """Each printed command composes and passes the app's checks (rows, seeds, budget, every row's training
    config with the GPU's overrides) as ``python -m cicfw.reproduce`` would run them, without training."""
    from cicfw.reproduction.app import check_plan, check_rows, compose_plan

    m = load_bench_script("gpu_check")
    m.main(["--license-study"])
    commands = [line.strip() for line in capsys.readouterr().out.splitlines()
                if line.strip().startswith("python -m cicfw.reproduce ")]
    for cmd in commands[:2]:
        cfg = compose_plan(shlex.split(cmd)[3:])
        rows, seeds = check_plan(cfg)
        check_rows(cfg, rows)
        assert len(seeds) == 1 and sorted(rows) == ["cil", "cil_bf16"]
        assert "trainer.accelerator=gpu" in list(cfg.budget.train)


def test_fp32_means_fp32_tf32_is_turned_off_for_training_and_driving(tmp_path):
    """TF32 (10-bit mantissas in fp32 matmuls and cuDNN convolutions on Ampere+ GPUs; PyTorch's default for
    cuDNN convolutions) is not licensed: a training and a checkpoint loaded to drive both turn it off. The
    flags exist on a CPU build too, so this runs anywhere."""
    import lightning as L

    from cicfw.model.checkpoint import load_model
    from cicfw.model.module import CICModule
    from cicfw.model.speed import SpeedConfig, apply_speed_from_config

    def tf32_on() -> None:
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
        torch.set_float32_matmul_precision("high")

    def tf32_off() -> bool:
        return (not torch.backends.cuda.matmul.allow_tf32 and not torch.backends.cudnn.allow_tf32
                and torch.get_float32_matmul_precision() == "highest")

    try:
        tf32_on()
        assert not tf32_off()
        model = CICModule()
        apply_speed_from_config(model, SpeedConfig(channels_last=False, compile=False, keep_memory=False),
                                {"accelerator": "cpu", "max_steps": 1}, 8, 1)
        assert tf32_off()

        trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_epochs=0,
                            accelerator="cpu", enable_model_summary=False)
        trainer.strategy.connect(model)
        trainer.save_checkpoint(tmp_path / "m.ckpt")
        tf32_on()
        load_model(tmp_path / "m.ckpt")
        assert tf32_off()
    finally:
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False
        torch.set_float32_matmul_precision("highest")
