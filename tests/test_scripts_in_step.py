"""The scripts are kept as near-copies: `diff sac_continuous.py jirl_sac_continuous.py` shows JIRL only,
`diff ppo_il.py trpo_il.py` shows TRPO only, and the regret code every script repeats is the same text in
all four; the lines of the paper's Alg. 1 that the code cites are cited alike wherever they are; `.ci/run`
runs the README's test command as printed. A change made to one copy only fails here."""

import ast
import re
from collections import defaultdict

import numpy as np
import pytest

from conftest import ROOT, load_script


def top_level(name: str) -> dict[str, str]:
    """Source text of every top-level function, class and single-name assignment of ROOT/name.py."""
    source = (ROOT / f"{name}.py").read_text()
    found = {}
    for node in ast.parse(source).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            found[node.name] = ast.get_source_segment(source, node)
        elif isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            found[node.targets[0].id] = ast.get_source_segment(source, node)
    return found


SAC, JIRL = top_level("sac_continuous"), top_level("jirl_sac_continuous")
JIRL_CHANGES = {"Args", "ReplayBuffer"}  # the two shared definitions JIRL extends, checked below
SHARED_BY_ALL = [  # the baseline, regret, checkpoint and early-stop code every script repeats
    "EVAL_SEED_OFFSET", "EPISODE_LIMIT", "claim_run_dir", "load_baseline", "check_baseline_action", "baseline_rollout", "paired_regret", "unpaired_regret",
    "write_checkpoint", "load_checkpoint", "flaw", "StopRequest", "ask_baseline", "kind", "raised", "CheckedEnv", "CheckedWriter", "OutputGuard", "start_tracking", "VideoTracker", "finish_tracking",
]


@pytest.mark.parametrize("script", ["sac_continuous", "jirl_sac_continuous", "ppo_il", "trpo_il"])
def test_a_script_imports_no_other_and_envs_only_where_it_runs_without(script):
    """Each script stands alone, to be copied into another project: it imports no other script nor
    anything else of this repository but `envs/`, and that only in a `try` whose `except ImportError`
    runs the script without it (as `test_script_copied_alone_runs_with_a_user_baseline` does for JIRL)."""
    tree = ast.parse((ROOT / f"{script}.py").read_text())
    ours = {p.stem for p in ROOT.glob("*.py")} | {p.parent.name for p in ROOT.glob("*/*.py")}  # the scripts, envs, deploy, benchmarks, tests

    def catches_import_error(handler: ast.ExceptHandler) -> bool:
        caught = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
        return any(isinstance(t, ast.Name) and t.id in ("ImportError", "ModuleNotFoundError") for t in caught)

    guarded = {id(node) for top in tree.body if isinstance(top, ast.Try) and any(map(catches_import_error, top.handlers)) for node in top.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for name in [alias.name for alias in node.names] if isinstance(node, ast.Import) else [node.module or "."]:
                root = name.split(".")[0]
                if root in ours:
                    assert root == "envs" and id(node) in guarded, f"{script}.py line {node.lineno} imports {name}"
                    found.append(name)
    assert found, "the project's env ids and baselines are imported where present"


def test_jirl_repeats_every_sac_definition_it_does_not_extend():
    assert set(SAC) <= set(JIRL), f"missing from the JIRL script: {sorted(set(SAC) - set(JIRL))}"
    drifted = [name for name in SAC if name not in JIRL_CHANGES and SAC[name] != JIRL[name]]
    assert drifted == [], f"edit these in both scripts: {drifted}"


def args_fields(name: str) -> dict[str, str]:
    """Each field of the script's Args as its source line (name, type, default) and its docstring."""
    source = (ROOT / f"{name}.py").read_text()
    body = next(n for n in ast.parse(source).body if isinstance(n, ast.ClassDef) and n.name == "Args").body
    return {
        node.target.id: ast.get_source_segment(source, node) + "\n" + ast.get_source_segment(source, doc)
        for node, doc in zip(body, body[1:])
        if isinstance(node, ast.AnnAssign) and isinstance(doc, ast.Expr)
    }


def test_jirl_args_keep_every_sac_field_default_and_docstring():
    sac_fields, jirl_fields = args_fields("sac_continuous"), args_fields("jirl_sac_continuous")
    own = {"exp_name", "learning_starts"}  # the script's name; JIRL acts with the gate before learning starts
    assert set(sac_fields) <= set(jirl_fields)
    drifted = [name for name in sac_fields if name not in own and sac_fields[name] != jirl_fields[name]]
    assert drifted == [], f"edit these Args fields in both scripts: {drifted}"
    assert {"gate_c", "gate_k", "penalty_sigma2", "guidance_steps"} <= set(jirl_fields) - set(sac_fields)


def test_jirl_buffer_samples_as_sacs_when_guidance_rows_weigh_fully():
    sac, jirl = load_script("sac_continuous"), load_script("jirl_sac_continuous")
    buffers = [sac.ReplayBuffer(50, 3, 1, seed=7), jirl.ReplayBuffer(50, 3, 1, seed=7)]
    rng = np.random.default_rng(0)
    for i in range(80):  # wraps around the capacity
        row = rng.normal(size=3), rng.uniform(-1, 1, size=1), float(rng.normal()), rng.normal(size=3), bool(i % 9 == 0)
        buffers[0].add(*row)
        buffers[1].add(*row, guidance=i % 2 == 0)
    for a, b in zip(buffers[0].sample(32), buffers[1].sample(32, guidance_weight=1.0)):
        assert a.equal(b)


@pytest.mark.parametrize("script", ["ppo_il", "trpo_il"])  # JIRL's copy: the first test
def test_the_trust_region_scripts_repeat_sacs_regret_code_word_for_word(script):
    other = top_level(script)
    drifted = [name for name in SHARED_BY_ALL if other.get(name) != SAC[name]]
    assert drifted == [], f"{script}.py differs from sac_continuous.py in {drifted}"


def test_trpo_il_repeats_every_ppo_il_definition_but_its_settings():
    ppo, trpo = top_level("ppo_il"), top_level("trpo_il")
    settings = {"TUNED", "DEFAULTS", "Args", "resolve_hyperparameters"}  # each method's own hyperparameters (PPO's minibatches)
    assert set(ppo) <= set(trpo), f"missing from trpo_il.py: {sorted(set(ppo) - set(trpo))}"
    drifted = [name for name in ppo if name not in settings and ppo[name] != trpo[name]]
    assert drifted == [], f"edit these in both scripts: {drifted}"


def test_ci_runs_the_readmes_test_command_as_printed():
    readme = (ROOT / "README.md").read_text()
    command = readme.split("Run the tests (after the first command):", 1)[1].split("```bash\n", 1)[1].split("\n```", 1)[0]
    assert " -m pytest " in command and command in (ROOT / ".ci" / "run").read_text().splitlines()


def test_each_line_of_algorithm_1_is_cited_for_the_same_step_everywhere():
    """Where the script, the car's loop or a test implements a line of the paper's Alg. 1, its comment cites it
    as "Alg. 1, line N: the step". The paper's algorithm2e listing numbers every line, the comment line
    before the agent's action is sampled for the fabricated transition included: line 9 stores the real
    transition and lines 12-14 the fabricated one. A number cited for two steps, or a step at two numbers,
    fails here (a test cited line 9 for the fabricated transition, and the script lines 11-13)."""
    cite = re.compile(r"Alg\. 1, lines? ([\d-]+): (the [\w']+(?: [\w']+)?)")
    steps, where = defaultdict(set), defaultdict(list)
    for path in sorted([*ROOT.glob("*.py"), *ROOT.glob("deploy/*.py"), *ROOT.glob("tests/*.py")]):
        for lines, step in cite.findall(path.read_text()):
            steps[lines].add(step)
            where[lines].append(path.name)
    assert dict(steps) == {"3": {"the baseline's action"}, "4": {"the gate"}, "9": {"the real transition"}, "12-14": {"the fabricated transition"}}, dict(where)
    assert {"jirl_sac_continuous.py", "jetracer.py"} <= set(where["9"]) & set(where["12-14"])  # the script and the car alike
