"""How the package installs and starts: every third-party import declared (core or its extra), a missing extra is
one line, `import pi0_torch` and `pi0-torch --help` import no torch, AutoModel knows the models, every command's
help works, the GPU tests and benchmark need none of the extras a bare GPU image lacks, and the shipped policy has a
name that works from anywhere. (`.ci/install-check` does the same from a wheel in a clean virtualenv.)"""

from __future__ import annotations

import ast
import importlib
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same parser as pytest's own dependency there
    import tomli as tomllib

from pi0_torch.cli import COMMANDS, main
from pi0_torch.utils.extras import DISTRIBUTIONS as EXTRA_DISTRIBUTIONS
from pi0_torch.utils.extras import EXTRAS, MissingExtraError, require_extra

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pi0_torch"
DISTRIBUTIONS = {"PIL": "pillow", **EXTRA_DISTRIBUTIONS}  # import name -> pip name, where they differ
LAZY_PACKAGES = ("pi0_torch", "pi0_torch.models", "pi0_torch.processing", "pi0_torch.runtime", "pi0_torch.data",
                 "pi0_torch.training", "pi0_torch.conversion")


def _requirement_name(requirement: str) -> str:
    return re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, check=False)


def test_every_third_party_import_is_declared_in_the_core_or_an_extra() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {_requirement_name(r) for r in project["dependencies"]}
    extras = {name: {_requirement_name(r) for r in requirements} for name, requirements in project["optional-dependencies"].items()}
    declared = core | set().union(*(extras[name] for name in EXTRAS))  # not [dev]: the package never needs test tools
    imported: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "pi0_torch":
                    imported.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    undeclared = {m: sorted(files) for m, files in imported.items()
                  if DISTRIBUTIONS.get(m, m).lower().replace("_", "-") not in declared}
    assert undeclared == {}
    assert {"tokenizers", "huggingface_hub", "torch", "transformers"} <= set(imported)  # the scan sees imports
    for extra, modules in EXTRAS.items():  # utils/extras.py checks exactly what pyproject.toml installs
        assert {DISTRIBUTIONS.get(m, m).replace("_", "-") for m in modules} == extras[extra] - {"pi0-torch"}, extra
    assert extras["all"] == {"pi0-torch"} and "pi0-torch" in extras["dev"]


def test_import_and_help_import_neither_torch_nor_transformers(tmp_path: Path) -> None:
    done = _python("import sys, pi0_torch, pi0_torch.cli\n"
                   "from pi0_torch.cli import build_parser\n"
                   "build_parser([])\n"
                   "print(sorted(m for m in ('torch', 'transformers', 'numpy') if m in sys.modules))", tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


@pytest.mark.parametrize("package", LAZY_PACKAGES)
def test_lazy_packages_export_every_public_name(package: str) -> None:
    """Each name resolves to the object of the module it names, `dir()` lists it, and the `TYPE_CHECKING` imports
    (what editors and type checkers see) are exactly the exported names from the same modules."""
    module = importlib.import_module(package)
    exports = module._EXPORTS
    assert set(module.__all__) - {"__version__"} == set(exports)
    for name, source in exports.items():
        assert getattr(module, name) is getattr(importlib.import_module(source), name)
        assert name in dir(module)
    with pytest.raises(AttributeError, match="has no attribute 'nothing_here'"):
        module.nothing_here  # noqa: B018
    tree = ast.parse(Path(module.__file__).read_text())
    (guard,) = [node for node in tree.body if isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING"]
    typed = {alias.name: node.module for node in guard.body for alias in node.names}
    assert typed == exports


@pytest.mark.parametrize("transformers_first", [False, True])
def test_auto_classes_know_the_models_once_pi0_torch_is_imported(tmp_path: Path, transformers_first: bool) -> None:
    """`import pi0_torch` registers the configs with AutoConfig (when transformers loads its registry, or at once
    if it already has) and the models with AutoModel (when a config exists): either import order works."""
    imports = ["import pi0_torch", "from transformers import AutoConfig, AutoModel"]
    code = "\n".join([*(reversed(imports) if transformers_first else imports),
                      "from pi0_torch import PI0FastConfig",
                      "folder = pi0_torch.demo_policy_dir()",
                      "print(type(AutoConfig.from_pretrained(folder)).__name__)",
                      "print(type(AutoModel.from_pretrained(folder)).__name__)",
                      "print(type(AutoModel.from_config(PI0FastConfig.from_preset('pi0_fast_small'))).__name__)"])
    done = _python(code, tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["PI0Config", "PI0ForActionGeneration", "PI0FastForActionGeneration"]


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help_of_every_command(command: str | None, capsys: pytest.CaptureFixture[str]) -> None:
    """`--help` formats (argparse %-formats help strings: a bare % once broke the top level's)."""
    with pytest.raises(SystemExit) as exit_:
        main(["--help"] if command is None else [command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: ") and (command is None or f" {command} " in out.splitlines()[0] + " ")
    if command is None:
        assert "95% intervals" in out and all(name in out for name in COMMANDS)


@pytest.mark.parametrize(("command", "missing", "extra"), [
    (["serve", "--model", "demo"], "websockets", "serve"),
    (["train", "--dataset", "x", "--model", "pi0_small", "--output-dir", "y"], "datasets", "train"),
    (["demo"], "gymnasium", "envs"),
    (["eval", "--policy", "expert", "--env", "pi0_torch/Reach-v0"], "gymnasium", "envs"),
    (["demos", "--env", "pi0_torch/Reach-v0"], "pandas", "train"),
    (["consolidate", "--checkpoint", "x"], "accelerate", "train"),
])
def test_a_command_without_its_extra_says_so_in_one_line(tmp_path: Path, command: list[str], missing: str, extra: str) -> None:
    """A module hidden from this process (as if not installed) makes the command stop with one line naming it and the
    extra that installs it, before any work (and before torch is imported: at once); its `--help` still works and
    says what to install (issue 38.17: it refused `--help`, and took 20-30 s to name the extra)."""
    done = _python(f"import sys\nsys.modules[{missing!r}] = None\n"  # import and find_spec both see it as absent
                   f"from pi0_torch.cli import main\ncode = main({command!r})\n"
                   f"assert 'torch' not in sys.modules or {command[0]!r} == 'eval', 'torch was imported'\nsys.exit(code)", tmp_path)
    assert (done.returncode, done.stdout) == (1, "")
    assert done.stderr == f"pi0-torch {command[0]} needs {missing}: pip install 'pi0-torch[{extra}]'\n"
    helped = _python(f"import sys\nsys.modules[{missing!r}] = None\n"
                     f"from pi0_torch.cli import main\nsys.exit(main([{command[0]!r}, '--help']))", tmp_path)
    assert helped.returncode == 0 and helped.stdout.startswith(f"usage: pi0-torch {command[0]}"), helped.stderr
    if command[0] != "eval":  # (eval needs an env's extra only for the env it runs)
        # the install line whole, as one line of the help (one that argparse wrapped slipped past install-check)
        assert f"pi0-torch {command[0]} needs {missing}: pip install 'pi0-torch[{extra}]'" in helped.stdout.splitlines()


GPU_IMAGE_LACKS = ("av", "datasets", "gymnasium", "websockets", "zstandard")  # (issue 26: the device machine's image)


def test_the_gpu_tests_and_the_benchmark_need_none_of_the_extras_a_gpu_image_lacks(tmp_path: Path) -> None:
    """docs/gpu.md's commands (benchmarks/gpu_check.sh) run where only torch, triton, transformers and the core packages
    are installed: the GPU and kernel tests are collected, and the benchmark, the doctor, the policy and the scripts
    gpu_check.sh runs are imported, with those extras' modules hidden."""
    tests = [str(ROOT / "tests" / name) for name in ("test_cuda.py", "test_kernels.py")]
    done = _python(
        "import sys\n"
        f"sys.modules.update(dict.fromkeys({GPU_IMAGE_LACKS!r}))\n"
        "import pytest\n"
        f"code = pytest.main(['-q', '--collect-only', '-p', 'no:cacheprovider', *{tests!r}])\n"
        "import pi0_torch.benchmark, pi0_torch.doctor, pi0_torch.runtime.policy\n"
        f"sys.path.insert(0, {str(ROOT / 'benchmarks')!r})\n"
        "import kernel_sweep, persistent_layers, persistent_mlp\n"
        "sys.exit(int(code))",
        tmp_path,
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert re.search(r"^\d+ tests collected", done.stdout, re.MULTILINE), done.stdout


@pytest.mark.parametrize("module, needs", [
    ("pi0_torch.training.lora", set()),
    ("pi0_torch.training.pi0_trainer", {"accelerate"}),
    ("pi0_torch.training.checkpoints", {"accelerate"}),
    ("pi0_torch.training.fsdp", {"accelerate"}),
])
def test_each_training_module_asks_only_for_what_it_uses(tmp_path: Path, module: str, needs: set[str]) -> None:
    """LoRA needs nothing of [train]: on a GPU image without `datasets` (issue 36) `apply_lora` failed to import,
    naming `datasets`. With every other module of the extras hidden, each module imports, and LoRA is applied to a
    small model and merged back."""
    hidden = sorted(set(GPU_IMAGE_LACKS) | set(EXTRAS["train"]) - needs)
    lora = ("from pi0_torch import PI0Config, PI0ForActionGeneration\n"
            "model = PI0ForActionGeneration(PI0Config.from_preset('pi0_small', num_hidden_layers=1))\n"
            "lora = trainable.apply_lora(model)\n"
            "assert type(trainable.merge_lora(lora)) is PI0ForActionGeneration\n") if module.endswith("lora") else ""
    done = _python(f"import sys\nsys.modules.update(dict.fromkeys({hidden!r}))\n"
                   f"import importlib\ntrainable = importlib.import_module({module!r})\n{lora}", tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]


def test_require_extra_names_the_feature_and_the_extra() -> None:
    with pytest.raises(MissingExtraError) as error:
        require_extra("serve", "pi0_torch.runtime.serving", modules=("websockets", "no_such_module_here"))
    assert str(error.value) == "pi0_torch.runtime.serving needs no_such_module_here: pip install 'pi0-torch[serve]'"
    assert isinstance(error.value, ImportError) and error.value.name == "no_such_module_here"
    require_extra("envs", "the tabletop envs")  # installed here: nothing raised
    with pytest.raises(ValueError, match="unknown extra 'gpu'"):
        require_extra("gpu", "x")


def test_the_shipped_policy_is_named_from_anywhere(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`demo` (eval / serve / demo) and `pi0_torch.demo_policy_dir()` work from any folder; the clone-relative path
    of older docs fails at once, pointing at them, instead of waiting on the hub."""
    from pi0_torch import PI0ForActionGeneration, demo_policy_dir
    from pi0_torch.runtime.rollout import LocalPolicy, load_policy

    monkeypatch.chdir(tmp_path)
    policy = load_policy("demo", connections=1)
    assert isinstance(policy, LocalPolicy) and policy.source == demo_policy_dir()
    assert policy.metadata["action_horizon"] == 16
    with pytest.raises(FileNotFoundError, match=r"pi0_torch.demo_policy_dir\(\) \(--policy demo"):
        PI0ForActionGeneration.from_pretrained("pi0_torch/demo_policy")


def test_the_simulator_extras_agree_on_one_mujoco_in_any_install_order() -> None:
    """Issue 63, first hour 4: `pip install '.[metaworld]'` then `'.[aloha]'` upgraded mujoco from 3.3.0 to 3.8.1
    (the newest dm-control needs it) and `pip check` failed: metaworld pins 3.3.0. Every simulator extra must accept
    metaworld's mujoco, and [aloha] must cap dm-control at a release that accepts it too (checked against the
    installed metaworld and dm-control's own requirements, where they are installed)."""
    import importlib.metadata

    from packaging.requirements import Requirement

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    wanted = {name: {Requirement(r).name: Requirement(r) for r in extras[name]} for name in ("metaworld", "aloha", "libero")}
    try:
        metaworld_mujoco = next(Requirement(r) for r in importlib.metadata.requires("metaworld") or ()
                                if Requirement(r).name == "mujoco")
        dm_control = importlib.metadata.version("dm_control")
        dm_control_mujoco = next(Requirement(r) for r in importlib.metadata.requires("dm_control") or ()
                                 if Requirement(r).name == "mujoco")
    except (importlib.metadata.PackageNotFoundError, StopIteration):
        pytest.skip("metaworld and dm-control are not installed (the dev extra)")
    pinned = next(iter(metaworld_mujoco.specifier)).version  # ("==3.3.0")
    for name, requirements in wanted.items():
        assert requirements["mujoco"].specifier.contains(pinned), (name, str(requirements["mujoco"]), pinned)
    cap = wanted["aloha"]["dm-control"].specifier
    assert any(spec.operator in ("<=", "<", "==") for spec in cap), f"[aloha] leaves dm-control uncapped: {cap}"
    if cap.contains(dm_control) and all(spec.version == dm_control for spec in cap if spec.operator == "<="):
        assert dm_control_mujoco.specifier.contains(pinned), (dm_control, str(dm_control_mujoco), pinned)


def test_a_numpy_downgrade_is_one_line_at_the_first_import_that_fails(monkeypatch: pytest.MonkeyPatch,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 63, first hour 6: openpi-client in the same environment pinned numpy<2, pandas then failed to import,
    and `train` printed pandas' traceback. Now one line names the package, numpy's version, the cause and the fix."""
    from pi0_torch import cli

    def pandas_built_for_numpy_2(name: str) -> Any:
        raise ValueError("numpy.dtype size changed, may indicate binary incompatibility. Expected 96 from C header, "
                         "got 88 from PyObject")

    monkeypatch.setattr(cli.importlib, "import_module", pandas_built_for_numpy_2)
    status = main(["doctor"])
    err = capsys.readouterr().err.strip()
    assert status == 1 and "\n" not in err, err
    assert re.match(r"pi0-torch doctor: error: a compiled package does not import with numpy [\d.]+ \(numpy.dtype size "
                    r"changed, .*\): it was built for another numpy major version\. A package pinned numpy here "
                    r"\(openpi-client pins numpy<2\): pip install --upgrade 'numpy>=2'", err), err
    other = ImportError("No module named 'x'")
    assert cli.numpy_mismatch(other) is None and cli.numpy_mismatch(ImportError("compiled using NumPy 1.x", name="pyarrow")
                                                                    ).startswith("pyarrow does not import with numpy")


def test_progress_bars_do_not_ask_for_ipywidgets(tmp_path: Path) -> None:
    """Issue 63, first hour 7: evaluate.ipynb warned that ipywidgets was missing (tqdm.auto's notebook bar wants it,
    and no extra brings it). Without ipywidgets every bar is tqdm's text bar, which warns nothing."""
    code = ("import importlib.util, sys\n"
            "find = importlib.util.find_spec\n"
            "importlib.util.find_spec = lambda name, *a: None if name == 'ipywidgets' else find(name, *a)\n"
            "import tqdm.std\nfrom pi0_torch.utils import progress\nassert progress.tqdm is tqdm.std.tqdm\n")
    run = _python(code, tmp_path)
    assert run.returncode == 0, run.stderr


@pytest.mark.parametrize("broken", ["raise RuntimeError('a broken triton build')", "raise SystemExit(3)",
                                    "__version__ = '0'  # (no triton.language)"])
def test_a_triton_that_does_not_import_is_set_aside(tmp_path: Path, broken: str) -> None:
    """Issue 63, round 5 item 9: a triton raising at import, or lacking `triton.language`, gave torch's own 40-line
    traceback at the first model import (torch's compiler imports triton); one raising `SystemExit` ended `doctor`
    with status 3 and no output. It is set aside now: models import and sample, the fused kernels are refused naming
    why, and doctor's triton row fails with that line."""
    (tmp_path / "triton").mkdir()
    (tmp_path / "triton" / "__init__.py").write_text(broken + "\n")
    code = ("import torch\nfrom pi0_torch.models import PI0Config, PI0ForActionGeneration\n"
            "from pi0_torch.benchmark import example_batch\nfrom pi0_torch.kernels import ops\n"
            "from pi0_torch.doctor import _triton_row\n"
            "model = PI0ForActionGeneration(PI0Config.from_preset('pi0_small')).eval()\n"
            "actions = model.generate_actions(**example_batch(model.config, 1, 1, torch.device('cpu')), num_steps=2)\n"
            "print(tuple(actions.shape), ops.triton_reason(torch.device('cuda')))\n"
            "try:\n    _triton_row()\nexcept ImportError as error:\n    print('row:', error)\n")
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=False,
                         env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.startswith("(1, 50, 32) the installed triton does not import ("), run.stdout
    assert "row: the installed triton does not import" in run.stdout and "Traceback" not in run.stderr, run.stdout
