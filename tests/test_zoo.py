"""``python -m detaug_gym.zoo build``: recipes, the plan (skip, resume, rebuild, refuse) and one real tiny build.

The build test runs every stage for real on the Newton suite (collection with the scripted expert in MuJoCo,
both augmentations, three 3-step trainings, a Free bench and the cards) at toy sizes, then checks what a rerun,
a changed recipe and ``--rebuild`` plan from the files it left.
"""

from __future__ import annotations

import json
import re

import pytest

from detaug_gym.envs.suites import SUITES
from detaug_gym.zoo import STAGES, Paths, Recipe, RecipeError, build_stages, main, plan, wall_estimate, write_stamp

TINY = """
suite = "newton"
tried = ["3 training steps: not enough (this test)"]
[collect]
demos = 2
[recovery]
demos = 1
seed = 500
action_noise = 0.3
noise_duty = 0.25
[augment_detaug]
copies = 1
limit = 1
[augment_demogen]
copies = 1
limit = 1
[train_base]
steps = 3
batch_size = 8
[train_detaug]
steps = 3
batch_size = 8
[train_demogen]
steps = {demogen_steps}
batch_size = 8
[evaluate]
episodes_per_task = 1
methods = ["scripted", "base", "detaug:labels=zero", "demogen"]
"""


def _recipe(tmp_path, text: str, suite: str = "newton") -> Recipe:
    path = tmp_path / f"{suite}.toml"
    path.write_text(text)
    return Recipe.load(suite, path)


@pytest.mark.parametrize("suite", list(SUITES))
def test_every_suite_has_a_recipe_its_commands_accept(suite):
    recipe = Recipe.load(suite)
    stages = build_stages(recipe, Paths.default(suite))
    assert list(stages) == list(STAGES)
    train = stages["train_detaug"].argv
    assert train[train.index("--init-from") + 1].endswith(f"base/{suite}")
    assert f"{suite}_detaug.hdf5" in train[train.index("--data") + 1]
    assert all(s.estimate_s > 0 for n, s in stages.items() if n != "cards")


@pytest.mark.parametrize("text, message", [
    ("[trian_base]\nsteps = 3\n", r"\[trian_base\] is not a stage"),
    ("[train_base]\nout = 'x'\n", r"sets out, which the zoo wires"),
    ("[collect]\nenv = 'x'\n", r"sets env, which the zoo wires"),
    ("[train_base]\nstepz = 3\n", r"\[train_base\]: unknown options --stepz 3"),
    ("[train_base]\nsteps = 'many'\n", r"\[train_base\]: .*invalid int value"),
    ("[collect]\ndemos = 0\n", r"\[collect\]: --demos must be >= 1"),
    ("[augment_detaug]\ncopiez = 2\n", r"\[augment_detaug\]: unknown options --copiez 2"),
    ("suite = 'goal'\n", r"declares suite 'goal'"),
    ("[cards]\nx = 1\n", r"\[cards\] takes no options"),
    ("tried = 'more steps'\n", r"tried must be a list of strings"),
])
def test_a_bad_recipe_is_refused_with_the_stage_and_the_reason(tmp_path, text, message):
    with pytest.raises(RecipeError, match=message):
        recipe = _recipe(tmp_path, text)
        build_stages(recipe, Paths(tmp_path / "d", tmp_path / "z", tmp_path / "w"))


def test_an_unknown_suite_or_missing_recipe_names_the_valid_ones(tmp_path):
    with pytest.raises(ValueError, match="valid suites: spatial, object"):
        Recipe.load("kitchen")
    with pytest.raises(RecipeError, match="recipes in .*: goal, long, newton, object, spatial"):
        Recipe.load("spatial", tmp_path / "missing.toml")


def test_foreign_output_is_never_overwritten(tmp_path):
    recipe = _recipe(tmp_path, TINY.format(demogen_steps=3))
    paths = Paths(tmp_path / "d", tmp_path / "z", tmp_path / "w")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "newton.hdf5").write_text("made by hand")
    stages = build_stages(recipe, paths)
    foreign = r"collect: .*newton.hdf5 exists but was not made by the zoo.*--rebuild collect"
    with pytest.raises(RecipeError, match=foreign):
        plan(stages, list(STAGES), [])
    steps = plan(stages, list(STAGES), ["collect"])
    assert [s.action for s in steps][:2] == ["rebuild", "run"]


def test_a_stage_whose_need_is_not_built_must_be_asked_for(tmp_path):
    stages = build_stages(_recipe(tmp_path, TINY.format(demogen_steps=3)),
                          Paths(tmp_path / "d", tmp_path / "z", tmp_path / "w"))
    with pytest.raises(RecipeError, match="train_base needs collect, recovery, which is not built"):
        plan(stages, ["train_base"], [])


def test_the_wall_estimate_runs_the_longest_chain_first():
    stages = build_stages(Recipe.load("spatial"), Paths.default("spatial"))
    steps = plan({n: s for n, s in stages.items()}, list(STAGES), list(STAGES))
    one, two = wall_estimate(steps, 1), wall_estimate(steps, 2)
    assert one == pytest.approx(sum(s.estimate_s for s in stages.values()))
    chain = sum(stages[n].estimate_s for n in ("collect", "augment_demogen", "train_demogen", "evaluate"))
    assert chain <= two < one  # two jobs: no faster than the longest chain, faster than one job


@pytest.fixture(scope="module")
def tiny_build(tmp_path_factory):
    root = tmp_path_factory.mktemp("zoo")
    recipe = root / "newton.toml"
    recipe.write_text(TINY.format(demogen_steps=3))
    flags = ["--suite", "newton", "--recipe", str(recipe), "--data", str(root / "data"), "--zoo", str(root / "zoo"),
             "--work", str(root / "work")]
    main(["build", *flags, "--jobs", "2"])
    return root, flags


@pytest.mark.slow
def test_a_tiny_build_runs_every_stage_and_writes_cards(tiny_build):
    root, _ = tiny_build
    for method in ("base", "detaug", "demogen"):
        folder = root / "zoo" / method / "newton"
        assert (folder / "model.pt").is_file() and (folder / "normalization.json").is_file()
        stamp = json.loads((folder / "zoo_stage.json").read_text())
        assert stamp["state"] == "done" and stamp["command"].startswith(f"python -m detaug_gym.train --method {method}")
        card = (folder / "README.md").read_text()
        assert card.startswith(f"# {method} / newton")
        n = re.search(r"solves (\d+) of (\d+) episodes", card)
        assert n and int(n.group(2)) == 1, card
        assert "python -m detaug_gym.collect --env Newton-PickPlace-v0" in card
        assert "| 0 | newton_cube |" in card
        # what was tried is listed under a missed target only (demogen has none)
        assert ("- 3 training steps: not enough (this test)" in card) == ("**missed**" in card)
    assert "- 3 training steps" in (root / "zoo" / "base" / "newton" / "README.md").read_text()  # 3 steps miss
    detaug_card = (root / "zoo" / "detaug" / "newton" / "README.md").read_text()
    assert "newton_detaug.hdf5" in detaug_card and "copies requested from 1 sources" in detaug_card
    records = [json.loads(line) for line in (root / "work" / "free" / "episodes.jsonl").read_text().splitlines()]
    assert sorted({r["method"] for r in records}) == ["base", "demogen", "detaug:labels=zero", "scripted"]


@pytest.mark.slow
def test_a_rerun_skips_a_changed_recipe_is_refused_and_rebuild_reruns_what_follows(tiny_build, capsys):
    root, flags = tiny_build
    main(["build", *flags, "--dry-run"])
    out = capsys.readouterr().out
    actions = [m for m in re.findall(r"^(\w+)\s+(\w+)\s", out, re.M) if m[0] in STAGES]
    assert actions == [(s, "done") for s in STAGES]

    paths = Paths(root / "data", root / "zoo", root / "work")
    changed = _recipe(root / "work", TINY.format(demogen_steps=4))
    with pytest.raises(RecipeError, match=r"train_demogen: .* made by another recipe.*--rebuild train_demogen"):
        plan(build_stages(changed, paths), list(STAGES), [])
    steps = plan(build_stages(changed, paths), list(STAGES), ["train_demogen"])
    assert {s.stage.name: s.action for s in steps} == {
        "collect": "done", "recovery": "done", "augment_detaug": "done", "augment_demogen": "done",
        "train_base": "done", "train_detaug": "done", "train_demogen": "rebuild", "evaluate": "rebuild",
        "cards": "rebuild"}

    stages = build_stages(Recipe.load("newton", root / "newton.toml"), paths)
    evaluate = json.loads(stages["evaluate"].stamp.read_text())
    write_stamp(stages["evaluate"], "running", stages)  # what a build writes as it starts a stage
    resumed = {s.stage.name: s.action for s in plan(stages, list(STAGES), [])}
    assert (resumed["train_demogen"], resumed["evaluate"], resumed["cards"]) == ("done", "resume", "rebuild")
    stages["evaluate"].stamp.write_text(json.dumps(evaluate))

    # a fresh clone: the checkpoints and their cards are committed, the demos and the evaluation are not
    for folder in ("data", "work"):
        (root / folder).rename(root / f"{folder}.away")
    try:
        fresh = {s.stage.name: (s.action, s.why) for s in plan(stages, None, [])}
        again = {s.stage.name: s.action for s in plan(stages, ["evaluate"], [])}
    finally:
        for folder in ("data", "work"):
            (root / f"{folder}.away").rename(root / folder)
    assert {n: a for n, (a, _) in fresh.items()} == {
        "collect": "skip", "recovery": "skip", "augment_detaug": "skip", "augment_demogen": "skip",
        "train_base": "done", "train_detaug": "done", "train_demogen": "done", "evaluate": "skip", "cards": "done"}
    assert fresh["collect"][1].startswith("not needed")
    assert (again["collect"], again["evaluate"], again["cards"]) == ("skip", "run", "done")
    with pytest.raises(RecipeError, match="collect would change what augment_detaug, augment_demogen, train_base"):
        plan(stages, ["collect"], ["collect"])

    # --rebuild train_base where the evaluation is absent: the evaluation runs anew, so the cards are stale too
    (root / "work").rename(root / "work.away")
    try:
        rebuilt = {s.stage.name: s.action for s in plan(stages, list(STAGES), ["train_base"])}
    finally:
        (root / "work.away").rename(root / "work")
    assert [rebuilt[n] for n in ("train_base", "train_detaug", "evaluate", "cards")] == [
        "rebuild", "rebuild", "run", "rebuild"]

    card = root / "zoo" / "base" / "newton" / "README.md"
    card.unlink()  # a deleted output is rebuilt
    main(["build", *flags, "--stages", "cards"])
    assert card.is_file()
    main(["build", *flags, "--dry-run"])
    assert "cards            done" in capsys.readouterr().out


@pytest.mark.slow
def test_the_finetune_experiment_trains_four_runs_and_evaluates_every_snapshot(tiny_build):
    import torch

    from detaug_gym.finetune import main as finetune
    from detaug_gym.models import load_checkpoint

    root, flags = tiny_build
    out, figure = root / "finetune", root / "finetune.png"
    args = ["--steps", "4", "--points", "2", "--episodes", "1", "--jobs", "2", "--recipe", str(root / "newton.toml"),
            "--data", str(root / "data"), "--zoo", str(root / "zoo"), "--out", str(out), "--figure", str(figure)]
    finetune(args)
    rows = json.loads((out / "curves.json").read_text())
    assert [(r["method"], r["mode"], r["step"]) for r in rows] == [("base", "-", 0)] + [
        (m, mode, s) for m, mode in (("detaug", "adapter"), ("detaug", "full"), ("demogen", "adapter"),
                                     ("demogen", "full")) for s in (2, 4)]
    assert all(r["n"] == 1 for r in rows)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "finetune.md").read_text().count("\n| ") == 1 + len(rows)
    base = load_checkpoint(root / "zoo" / "base" / "newton").network.state_dict()
    for mode, frozen in (("adapter", True), ("full", False)):
        tuned = load_checkpoint(out / f"detaug_{mode}" / "snapshots" / "step_000004").network.state_dict()
        assert torch.equal(base["dit.blocks.0.attn.qkv.weight"], tuned["dit.blocks.0.attn.qkv.weight"]) \
            == frozen
    with pytest.raises(SystemExit, match="multiple of --points"):
        finetune(["--steps", "5", "--points", "2"])
