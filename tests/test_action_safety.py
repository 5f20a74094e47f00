"""Issue 28, class 4 (and the RTC items of class 9): a policy never hands back NaN or inf actions, and refuses, by
name, the real-time chunking inputs that drove its flow there.

- Out-of-range inputs (a previous chunk far outside the model's action range, a guidance clip of inf or 1e30, a
  noise scale of 1e30) are refused with a one-line `ValueError` naming the field, at the model API and through the
  policy and its server.
- Whatever else makes a chunk non-finite (NaN weights, a model that diverges), the policy withholds that chunk with an
  `UnsafeActionsError` naming the cause; the other observations of its batch get their actions, over the websocket
  too.
- Issue 63, round 5 item 5: absurd but finite norm stats are refused at load, and a finite chunk beyond the policy's
  bounds (±1000 in the normalized space; `max_abs_action` in robot units) is withheld the same way.
"""

from __future__ import annotations

import json
import re
import threading
from typing import Any

import numpy as np
import pytest
import torch
import websockets.sync.client
from conftest import HORIZON, tiny_policy

from pi0_torch.kernels import ops
from pi0_torch.inference.rtc import MAX_GUIDANCE, MAX_PREVIOUS_ACTION
from pi0_torch.processing.normalization import NormStats
from pi0_torch.processing.processing_pi0 import PI0Processor
from pi0_torch.runtime.action_safety import UnsafeActionsError
from pi0_torch.runtime.observation_formats import ObservationError
from pi0_torch.runtime.policy import PI0Policy
from pi0_torch.runtime.serving import PolicyServer, pack_message, unpack_message

OBSERVATION = {"images": {"base_0_rgb": np.zeros((32, 32, 3), np.uint8)}, "state": np.ones(3), "prompt": "reach"}
PREVIOUS = np.linspace(-1, 1, HORIZON * 3, dtype=np.float32).reshape(HORIZON, 3)
CONTINUATION = {"previous_actions": PREVIOUS, "execution_horizon": 2, "inference_delay": 2}


@pytest.fixture(scope="module")
def policy() -> PI0Policy:
    return tiny_policy(rtc_max_delay=0)


# ---------------------------------------------------------------------------------------------------- inputs


@pytest.mark.parametrize(("previous", "message"), [
    (1e3, r"previous_actions \(normalized\): values up to 2e\+03 .* within ±100"),  # returned actions of 980
    (1e20, r"previous_actions \(normalized\): values up to 2e\+20"),  # returned all-NaN actions
    # (was named 'observation.actions (normalized)')
    (3e38, r"previous_actions \(normalized\): has values beyond float32's range \(±3.4e38\) at indices \[\(5, 1\)\]"),
    (np.inf, r"previous_actions: contains NaN or inf"),
])
def test_previous_actions_beyond_the_models_range_are_refused_by_name(policy: PI0Policy, previous: float, message: str) -> None:
    chunk = PREVIOUS.copy()
    chunk[5, 1] = previous
    with pytest.raises(ObservationError, match=message) as refused:
        policy.infer({**OBSERVATION, **CONTINUATION, "previous_actions": chunk})
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize(("state", "message"), [
    ([1e30, 0.0, 0.0], r"observation\.state: dims \[0\] normalize to [\d.]+e\+30 \(1e\+30 raw\), beyond ±1000"),
    (np.array([np.iinfo(np.uint64).max, 0, 0], np.uint64), r"observation\.state: dims \[0\] normalize to [\d.]+e\+19"),
    ([0.0, -5e3, 0.0], r"observation\.state: dims \[1\] normalize to -"),
])
def test_an_absurd_state_is_refused_by_name(policy: PI0Policy, state: Any, message: str) -> None:
    """Issue 38.9: `state=[1e30, 0, 0]` (or a uint64 max) gave actions of 1e30 as a normal reply. A state more than
    `MAX_NORMALIZED_STATE` from 0 in the model's normalized space is refused, naming the dims; a state within it is not."""
    with pytest.raises(ObservationError, match=message) as refused:
        policy.infer({**OBSERVATION, "state": state})
    assert "\n" not in str(refused.value)
    assert np.isfinite(policy.infer({**OBSERVATION, "state": [3.0, -3.0, 1.0]})["actions"]).all()


@pytest.mark.parametrize("guidance", [np.inf, 1e30, -1.0, MAX_GUIDANCE * 2])
def test_a_guidance_clip_outside_its_range_is_refused(policy: PI0Policy, guidance: float) -> None:
    with pytest.raises(ValueError, match=r"rtc_max_guidance must be a finite number >= 0 and <= 100"):
        PI0Policy(policy.model, policy.processor, rtc_max_guidance=guidance)
    batch = policy.prepare(OBSERVATION).inputs
    previous = torch.zeros(1, HORIZON, policy.model.config.action_dim)
    with pytest.raises(ValueError, match=r"rtc_max_guidance must be a finite number >= 0 and <= 100"):
        policy.model.generate_actions(**batch, previous_actions=previous, execution_horizon=2, rtc_max_guidance=guidance)


def test_the_model_api_refuses_a_previous_chunk_beyond_its_range(policy: PI0Policy) -> None:
    batch = policy.prepare(OBSERVATION).inputs
    previous = torch.zeros(1, HORIZON, policy.model.config.action_dim)
    previous[0, 3, 2] = MAX_PREVIOUS_ACTION * 10
    with pytest.raises(ValueError, match=r"previous_actions: values up to 1e\+03 \(at index \(0, 3, 2\)\)"):
        policy.model.generate_actions(**batch, previous_actions=previous, execution_horizon=2)
    with pytest.raises(ValueError, match=r"rtc_method must be one of \('guidance', 'conditioning'\), got ''"):
        policy.model.generate_actions(**batch, previous_actions=previous * 0, execution_horizon=2, rtc_method="")


@pytest.mark.parametrize("scale", [1e30, np.inf, -1.0])
def test_a_noise_scale_outside_its_range_is_refused(policy: PI0Policy, scale: float) -> None:
    with pytest.raises(ValueError, match=r"noise_scale must be a finite number >= 0 and <= 10"):
        PI0Policy(policy.model, policy.processor, noise_scale=scale)


@pytest.mark.parametrize(("method", "message"), [
    ("", r"rtc_method: expected one of \['guidance', 'conditioning'\] .*, got ''"),  # silently took the default
    (np.array(["guidance", "guidance"]), r"rtc_method: expected one of .*, got array\("),  # 'The truth value...'
    (np.array(3), r"rtc_method: expected one of .*, got 3"),
])
def test_a_bad_rtc_method_is_named(policy: PI0Policy, method: Any, message: str) -> None:
    with pytest.raises(ObservationError, match=message):
        policy.prepare({**OBSERVATION, **CONTINUATION, "rtc_method": method})
    assert policy.prepare({**OBSERVATION, **CONTINUATION, "rtc_method": np.array("guidance")}).continuation.method == "guidance"


# ---------------------------------------------------------------------------------------------------- outputs


def _nan_weights(policy: PI0Policy, monkeypatch: pytest.MonkeyPatch) -> None:  # (each test has its own policy)
    with torch.no_grad():
        next(iter(policy.model.parameters()))[..., 0] = float("nan")


def _diverging_model(policy: PI0Policy, monkeypatch: pytest.MonkeyPatch) -> None:
    generate = policy.model.generate_actions
    monkeypatch.setattr(policy.model, "generate_actions", lambda **kw: generate(**kw) * float("nan"))


def _diverging_guidance(policy: PI0Policy, monkeypatch: pytest.MonkeyPatch) -> None:
    generate = policy.model.generate_actions
    monkeypatch.setattr(policy.model, "generate_actions",
                        lambda **kw: generate(**kw) * (float("inf") if "previous_actions" in kw else 1.0))


CAUSES = {
    "NaN weights": (_nan_weights, {}, r"the model's weights hold NaN/inf \(the first: "),
    "model": (_diverging_model, {}, r"the model returned NaN/inf from finite inputs \(float32 weights"),
    "guidance": (_diverging_guidance, CONTINUATION, r"real-time chunking guidance diverged \(rtc_max_guidance 5"),
}


@pytest.mark.parametrize("cause", sorted(CAUSES))
def test_non_finite_actions_are_withheld_naming_the_cause(cause: str, monkeypatch: pytest.MonkeyPatch) -> None:
    policy = tiny_policy(rtc_max_delay=0)
    break_it, fields, message = CAUSES[cause]
    break_it(policy, monkeypatch)
    with pytest.raises(UnsafeActionsError, match="the action chunk holds .* NaN/inf values and was withheld; cause: "
                                                 + message) as withheld:
        policy.infer({**OBSERVATION, **fields})
    assert "\n" not in str(withheld.value)


@pytest.mark.parametrize(("field", "value"), [("mean", 3.3e38), ("std", 1e38), ("q99", 1e30), ("q01", -2.0**25)])
def test_absurd_but_finite_norm_stats_are_refused_at_load(tmp_path: Any, field: str, value: float) -> None:
    """`norm_stats.actions.mean[0] = 3.3e38` (or std 1e38) in a policy folder made `serve` reply actions of 3.3e38 and
    `eval` report "jerk inf". Statistics beyond ±2^24 robot units are refused at load, naming the file, the field
    and the dim."""
    from pi0_torch.processing.normalization import load_openpi_norm_stats, save_openpi_norm_stats

    entry = {"mean": [0.0, 1.0], "std": [1.0, 1.0], "q01": [-1.0, 0.0], "q99": [1.0, 2.0]}
    path = save_openpi_norm_stats(tmp_path, {key: NormStats.from_dict(entry) for key in ("state", "actions")})
    document = json.loads(path.read_text())
    document["norm_stats"]["actions"][field][1] = value
    path.write_text(json.dumps(document))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: NormStats.{field}\[1\] is .* beyond ±16777216 "
                                         r"\(2\^24\) in the robot's units"):
        load_openpi_norm_stats(tmp_path)


def test_an_absurd_min_norm_scale_is_refused() -> None:
    from pi0_torch.processing.tokenization import build_test_tokenizer

    stats = {key: NormStats(mean=np.zeros(3), std=np.ones(3)) for key in ("state", "actions")}
    with pytest.raises(ValueError, match=r"min_norm_scale must be .*<= 1\.67772e\+07.*got 1e\+30"):
        PI0Processor(build_test_tokenizer(), camera_names=["base_0_rgb"], norm_stats=stats, min_norm_scale=1e30)


def test_a_chunk_beyond_the_normalized_bound_is_withheld(monkeypatch: pytest.MonkeyPatch) -> None:
    """A finite chunk the model returns far outside its normalized range (a broken model or stats) is withheld, naming
    the bound, the largest value and where; a chunk within it is returned."""
    policy = tiny_policy(rtc_max_delay=0)
    model_actions = policy.model_actions
    scale = {"by": 1.0}
    monkeypatch.setattr(policy, "model_actions", lambda batch, **options: model_actions(batch, **options) * scale["by"])
    assert np.isfinite(policy.infer(OBSERVATION)["actions"]).all()
    scale["by"] = 1e6
    with pytest.raises(UnsafeActionsError, match=r"^the action chunk was withheld: \d+ values beyond ±1000 in the "
                                                 r"model's normalized space, .*; the largest -?[\d.e+]+ at step \d+, dim \d"):
        policy.infer(OBSERVATION)


def test_max_abs_action_bounds_the_chunks_in_robot_units(tmp_path: Any) -> None:
    """`max_abs_action` in a folder's policy_settings.json bounds every action in robot units: a chunk beyond it is
    withheld (the server replies the line instead of actions); a bound the actions keep changes nothing."""
    from dataclasses import replace

    from pi0_torch.runtime.policy_settings import PolicySettings

    policy = tiny_policy(rtc_max_delay=0)
    seeded = {**OBSERVATION, "noise_seed": 7}
    actions = policy.infer(seeded)["actions"]
    policy.settings = replace(policy.settings, max_abs_action=float(np.abs(actions).max()) * 2)
    np.testing.assert_array_equal(policy.infer(seeded)["actions"], actions)
    policy.settings = replace(policy.settings, max_abs_action=float(np.abs(actions).max()) / 2)
    with pytest.raises(UnsafeActionsError, match=r"^the action chunk was withheld: \d+ values beyond ±[\d.e+-]+ robot units "
                                                 r"\(the policy's max_abs_action, policy_settings.json\)"):
        policy.infer(OBSERVATION)
    (tmp_path / "policy_settings.json").write_text('{"max_abs_action": -1}')
    with pytest.raises(ValueError, match=r"policy_settings.json: max_abs_action must be"):
        PolicySettings.load(tmp_path)


# (the persistent launch runs in triton's interpreter here: TRITON_INTERPRET=1, the repository's conftest.py)
needs_interpreted_kernels = pytest.mark.skipif(ops.triton_reason(torch.device("cpu")) is not None,
                                               reason=str(ops.triton_reason(torch.device("cpu"))))


@needs_interpreted_kernels
def test_a_persistent_launch_that_abandoned_a_wait_is_named_and_its_chunk_withheld(monkeypatch: pytest.MonkeyPatch) -> None:
    """`sampling_kernels="persistent"`: a launch that waited too long (a synchronization fault on a GPU) returns NaN
    rather than hang, and so does every later one in the process (`kernels.persistent.watchdog`): a plan verified
    before that happened now gets its chunk withheld, naming the launch; a plan verified after it is refused."""
    from pi0_torch.kernels import persistent

    monkeypatch.setattr(persistent, "_watches", {})  # (this test's watch, not the process's)
    policy = tiny_policy(rtc_max_delay=0)
    policy.model.sampling_kernels = "persistent"
    assert np.isfinite(policy.infer(OBSERVATION)["actions"]).all()  # (verified against the unfused path, then kept)
    persistent.watchdog(policy.model.device)[0] = 1  # (as a wait given up by the kernel sets it)
    with pytest.raises(UnsafeActionsError, match=r"withheld; cause: persistent launch abandoned a wait that did not end "
                                                 r".*\(sampling_kernels='auto' samples without it\)"):
        policy.infer(OBSERVATION)
    with pytest.raises(ValueError, match="sampling_kernels='persistent' cannot run sampling .*its persistent launch "
                                         "abandoned a wait"):
        policy.model.generate_actions(**policy._batch([policy.prepare(OBSERVATION)]), num_steps=3)  # (a new plan)


@needs_interpreted_kernels
def test_auto_leaves_a_persistent_launch_that_abandoned_a_wait(monkeypatch: pytest.MonkeyPatch,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    """Under "auto" where the fused kernels apply (as on CUDA in bf16), an eager chunk of one sample takes the
    persistent launch. The chunk in which a launch abandons a wait is withheld, naming the launch; from the next chunk
    on "auto" samples with five launches per decoder layer there (logged once), and the chunks are fine again."""
    from pi0_torch.inference import checks
    from pi0_torch.kernels import persistent

    monkeypatch.setattr(persistent, "_watches", {})  # (this test's watch, not the process's)
    monkeypatch.setattr(checks, "_AVOIDED", set())
    policy = tiny_policy(rtc_max_delay=0)
    model = policy.model
    assert model.sampling_kernels == "auto"
    monkeypatch.setattr(model, "fused_steps_reason", lambda *args: None)
    assert np.isfinite(policy.infer(OBSERVATION)["actions"]).all()
    assert [plan.persistent for plan, _ in model._fused_refusals] == [True]  # (verified, then kept)

    launch = persistent.expert_layers_

    def gives_up(x: torch.Tensor, *args: Any, **options: Any) -> None:  # (a fault on the GPU: its waits give up)
        persistent.watchdog(x.device)[0] = 1
        launch(x, *args, **options)

    monkeypatch.setattr(persistent, "expert_layers_", gives_up)
    with pytest.raises(UnsafeActionsError, match=r"withheld; cause: persistent launch abandoned a wait that did not end "
                                                 r".*\(sampling_kernels='auto' samples without it from the next chunk\)"):
        policy.infer(OBSERVATION)
    with caplog.at_level("WARNING", logger="pi0_torch.inference.checks"):
        for _ in range(2):
            assert np.isfinite(policy.infer(OBSERVATION)["actions"]).all()
    assert [plan.persistent for plan, _ in model._fused_refusals] == [True, False]  # (five launches, verified)
    assert [record.getMessage() for record in caplog.records] == [
        "a persistent launch on cpu abandoned a wait that did not end (a synchronization fault of "
        "pi0_torch.kernels.persistent on this GPU: please report it); sampling_kernels='auto' runs five launches per "
        "decoder layer there from now on"]


def test_a_batch_keeps_the_chunks_that_are_fine(monkeypatch: pytest.MonkeyPatch) -> None:
    """One observation whose chunk is non-finite fails alone: the others of its batch get exactly the actions they
    get on their own."""
    policy = tiny_policy(rtc_max_delay=0)
    requests = [{**OBSERVATION, "noise_seed": seed} for seed in (1, 2, 3)]
    alone = [policy.infer(request)["actions"] for request in requests]
    model_actions = policy.model_actions

    def second_is_nan(batch: Any, **options: Any) -> np.ndarray:
        chunks = model_actions(batch, **options)
        chunks[1, 0, 0] = np.nan
        return chunks

    monkeypatch.setattr(policy, "model_actions", second_is_nan)
    with pytest.raises(UnsafeActionsError, match="^observation 1 of a batch of 3: ") as withheld:
        policy.infer_prepared([policy.prepare(request) for request in requests])
    outcomes = withheld.value.outcomes
    assert isinstance(outcomes[1], UnsafeActionsError)
    for index in (0, 2):  # (batched matrix products round differently in the last bits)
        np.testing.assert_allclose(outcomes[index]["actions"], alone[index], rtol=1e-5, atol=1e-6)


def test_the_server_sends_the_reason_instead_of_actions(monkeypatch: pytest.MonkeyPatch) -> None:
    """Over the websocket, batched with good requests: the client whose chunk was withheld gets one line naming the
    cause, the others their actions, and the same connection is served next time."""
    policy = tiny_policy(rtc_max_delay=0)
    model_actions = policy.model_actions

    def seed_13_is_nan(batch: Any, **options: Any) -> np.ndarray:
        chunks = model_actions(batch, **options)
        noise = options.get("noise")
        if noise is not None:
            for row in range(len(chunks)):
                if torch.equal(noise[row], policy.noise_scale * torch.randn(noise.shape[1:], generator=torch.Generator().manual_seed(13))):
                    chunks[row] = np.nan
        return chunks

    monkeypatch.setattr(policy, "model_actions", seed_13_is_nan)
    replies: dict[int, Any] = {}
    barrier = threading.Barrier(3)

    def client(port: int, seed: int) -> None:
        with websockets.sync.client.connect(f"ws://127.0.0.1:{port}", max_size=None) as ws:
            unpack_message(ws.recv(timeout=30))
            barrier.wait(timeout=30)
            ws.send(pack_message({**OBSERVATION, "noise_seed": seed}))
            reply = ws.recv(timeout=60)
            replies[seed] = reply if isinstance(reply, str) else unpack_message(reply)
            if seed == 13:
                ws.send(pack_message({**OBSERVATION, "noise_seed": 14}))
                replies[14] = unpack_message(ws.recv(timeout=60))

    with PolicyServer(policy, port=0, max_batch_size=3).serve_in_thread() as port:
        threads = [threading.Thread(target=client, args=(port, seed)) for seed in (12, 13, 15)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
    assert replies[13].startswith("no actions: ") and "cause: the model returned NaN/inf" in replies[13], replies[13]
    for seed in (12, 14, 15):
        assert np.isfinite(replies[seed]["actions"]).all() and replies[seed]["actions"].shape == (HORIZON, 3)


def test_a_pi0_fast_policy_withholds_non_finite_chunks_too(monkeypatch: pytest.MonkeyPatch) -> None:
    from pi0_torch import FASTActionTokenizer, PI0FastConfig, PI0FastForActionGeneration, PI0FastProcessor
    from pi0_torch.processing.tokenization import build_test_tokenizer
    from pi0_torch.runtime.policy_fast import PI0FastPolicy

    rng = np.random.default_rng(0)
    fast = FASTActionTokenizer.fit([np.cumsum(rng.normal(0, .1, (10, 8)), 0) for _ in range(100)], vocab_size=256)
    stats = {key: NormStats(mean=np.zeros(8), std=np.ones(8), q01=-np.ones(8), q99=np.ones(8)) for key in ("state", "actions")}
    config = PI0FastConfig.from_preset("pi0_fast_small")
    torch.manual_seed(0)
    policy = PI0FastPolicy(PI0FastForActionGeneration(config),
                           PI0FastProcessor.from_config(config, build_test_tokenizer(1024), fast, stats), num_steps=4)
    observation = {"images": {"base_0_rgb": np.zeros((32, 32, 3), np.uint8)}, "state": np.zeros(8), "prompt": "go"}
    extract = policy.processor.extract_actions
    monkeypatch.setattr(policy.processor, "extract_actions", lambda tokens, **options: extract(tokens, **options) * np.nan)
    # a π0-FAST chunk of finite weights is not finite only when its tokens do not decode (tests/test_pi0_fast_serving.py)
    with pytest.raises(UnsafeActionsError, match="withheld; cause: the generated tokens decode to no action chunk"):
        policy.infer(observation)
