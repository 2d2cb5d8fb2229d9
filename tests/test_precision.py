"""Precision follows the hardware: bf16 autocast only where the CPU does bf16 natively (no timing here)."""

from __future__ import annotations

import json

import pytest
import torch

from drivingscene import precision
from drivingscene.precision import (
    CACHE_NAME,
    ENV_VAR,
    CpuPrecision,
    cpu_decision,
    cpu_flags_summary,
    decide,
    describe_precision,
    read_cpuinfo,
    resolve_amp,
)

AVX2 = "fpu sse sse2 avx fma avx2 f16c"
ZEN4 = AVX2 + " avx512f avx512bw avx512vl avx512_vnni avx512_bf16"
SAPPHIRE_RAPIDS = ZEN4 + " amx_tile amx_int8 amx_bf16"


def cpuinfo(tmp_path, flags: str, model: str = "AMD EPYC", family: int = 25, name: str = "cpuinfo"):
    path = tmp_path / name
    block = f"processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: {family}\nmodel name\t: {model}\nflags\t\t: {flags}\n\n"
    path.write_text(block + block.replace("processor\t: 0", "processor\t: 1"))
    return path


class Measure:
    """A fake measurement: (float32 s, bf16 s), counting its calls."""

    def __init__(self, fp32_s: float = 2e-3, bf16_s: float = 1e-3):
        self.result, self.calls = (fp32_s, bf16_s), 0

    def __call__(self):
        self.calls += 1
        return self.result


@pytest.fixture(autouse=True)
def no_env_force(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


@pytest.fixture
def machine(monkeypatch):
    """Make this machine's CPU decision whatever a test sets."""

    def use(decision: CpuPrecision):
        monkeypatch.setattr(precision, "machine_cpu_decision", lambda: decision)
        return decision

    return use


NO_BF16 = CpuPrecision(False, (), "AVX2", "no native bf16")
NATIVE = CpuPrecision(True, ("avx512_bf16",), "AVX512", "native bf16 (not measured)")


# --- the decision from the flags ---------------------------------------------------------------


@pytest.mark.parametrize("flags", [AVX2, AVX2 + " avx512f avx512bw avx512vl", "fp asimd sve"])
def test_no_native_bf16_means_float32_without_measuring(flags):
    measure = Measure()
    decision = decide(frozenset(flags.split()), "AVX2", True, measure)
    assert decision.bf16 is False and decision.native == () and measure.calls == 0
    assert decision.describe() == "float32 (CPU AVX2, no native bf16)"


@pytest.mark.parametrize("flags, native", [(ZEN4, ("avx512_bf16",)), (SAPPHIRE_RAPIDS, ("avx512_bf16", "amx_bf16"))])
def test_native_bf16_confirmed_by_the_measurement(flags, native):
    measure = Measure(fp32_s=2e-3, bf16_s=1e-3)
    decision = decide(frozenset(flags.split()), "AVX512", True, measure)
    assert decision.bf16 is True and decision.native == native and measure.calls == 1
    assert decision.describe().startswith("bf16 autocast (CPU AVX512 with AVX512_BF16")
    assert (decision.float32_ms, decision.bf16_ms) == (2.0, 1.0)


def test_native_bf16_measured_slower_is_float32():
    decision = decide(frozenset(ZEN4.split()), "AVX512", True, Measure(fp32_s=1e-3, bf16_s=5e-3))
    assert decision.bf16 is False and "slower" in decision.reason


def test_native_bf16_without_measurement_or_with_a_failing_one():
    assert decide(frozenset(ZEN4.split()), "AVX512", True, measure=None).bf16 is True

    def broken():
        raise RuntimeError("no bf16 kernel")

    decision = decide(frozenset(ZEN4.split()), "AVX512", True, broken)
    assert decision.bf16 is False and "no bf16 kernel" in decision.reason


def test_onednn_without_bf16_wins_over_the_flags():
    measure = Measure()
    assert decide(frozenset(ZEN4.split()), "AVX512", False, measure).bf16 is False and measure.calls == 0


def test_unknown_flags_fall_back_to_onednn_and_the_measurement():
    assert decide(None, "AVX512", True, Measure(2e-3, 1e-3)).bf16 is True
    assert decide(None, "AVX512", True, Measure(1e-3, 2e-3)).bf16 is False
    assert decide(None, "DEFAULT", False, Measure()).bf16 is False
    assert decide(None, "DEFAULT", None, Measure()).bf16 is False


def test_read_cpuinfo_x86_arm_and_missing(tmp_path):
    model, flags = read_cpuinfo(cpuinfo(tmp_path, ZEN4, "AMD EPYC 9654"))
    assert model == "AMD EPYC 9654" and {"avx2", "avx512_bf16"} <= flags and "processor" not in flags
    arm = tmp_path / "arm"
    arm.write_text("processor\t: 0\nBogoMIPS\t: 2100.00\nFeatures\t: fp asimd sve bf16 i8mm\nCPU implementer\t: 0x41\n")
    assert read_cpuinfo(arm)[1] == frozenset("fp asimd sve bf16 i8mm".split())
    assert decide(read_cpuinfo(arm)[1], "SVE256", True, Measure(2e-3, 1e-3)).native == ("bf16",)
    assert read_cpuinfo(tmp_path / "absent")[1] is None


def test_flags_summary(tmp_path):
    assert cpu_flags_summary(cpuinfo(tmp_path, AVX2)) == "CPU family 25, flags AVX2 FMA (no AVX-512, no native bf16)"
    summary = cpu_flags_summary(cpuinfo(tmp_path, SAPPHIRE_RAPIDS, family=6))
    assert summary == "CPU family 6, flags AVX2 FMA AVX512F AVX512_VNNI AVX512_BF16 AMX_TILE AMX_BF16"


# --- the cache -----------------------------------------------------------------------------------


def test_cache_round_trip(tmp_path):
    info, cache = cpuinfo(tmp_path, ZEN4), tmp_path / "cache"
    measure = Measure()
    first = cpu_decision(info, cache, measure, capability="AVX512", onednn_bf16=True)
    again = cpu_decision(info, cache, measure, capability="AVX512", onednn_bf16=True)
    assert first == again and first.bf16 is True and measure.calls == 1  # measured once per machine
    data = json.loads((cache / CACHE_NAME).read_text())
    (entry,) = data["entries"].values()
    assert entry["bf16"] is True and entry["cpu"] == "AMD EPYC" and entry["torch"] == torch.__version__
    # another CPU (other flags) sharing the cache directory gets its own entry; the first stays
    other = cpu_decision(cpuinfo(tmp_path, AVX2, name="other"), cache, measure, capability="AVX2", onednn_bf16=False)
    assert other.bf16 is False and measure.calls == 1
    assert len(json.loads((cache / CACHE_NAME).read_text())["entries"]) == 2
    assert cpu_decision(info, cache, measure, capability="AVX512", onednn_bf16=True) == first and measure.calls == 1


def test_cache_key_includes_torch_version():
    flags = frozenset(AVX2.split())
    assert precision.cache_key("AMD EPYC", flags, "2.13.0") != precision.cache_key("AMD EPYC", flags, "2.14.0")
    assert precision.cache_key("AMD EPYC", flags) != precision.cache_key("AMD EPYC", flags | {"avx512_bf16"})


@pytest.mark.parametrize(
    "text",
    [
        "{not json",
        "[1, 2]",
        '{"version": 1, "entries": []}',
        '{"version": 999, "entries": {}}',
        "KEY",  # this CPU's entry, malformed
    ],
)
def test_corrupt_cache_is_ignored_and_replaced(tmp_path, text):
    info, cache = cpuinfo(tmp_path, ZEN4), tmp_path / "cache"
    cache.mkdir()
    key = precision.cache_key(*read_cpuinfo(info))
    if text == "KEY":
        text = json.dumps({"version": 1, "entries": {key: {"bf16": "yes", "native": 3}}})
    (cache / CACHE_NAME).write_text(text)
    measure = Measure()
    decision = cpu_decision(info, cache, measure, capability="AVX512", onednn_bf16=True)
    assert decision.bf16 is True and measure.calls == 1
    assert json.loads((cache / CACHE_NAME).read_text())["entries"][key]["bf16"] is True


def test_unwritable_cache_decides_anyway(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory would be")
    measure = Measure()
    for _ in range(2):  # nothing cached: decided again each time
        assert cpu_decision(cpuinfo(tmp_path, ZEN4), blocker / "sub", measure, "AVX512", True).bf16 is True
    assert measure.calls == 2


def test_cache_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert precision.cache_dir() == tmp_path / "drivingscene"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert precision.cache_dir().parts[-2:] == (".cache", "drivingscene")


def test_cpu_decision_defaults_to_the_xdg_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    cpu_decision(cpuinfo(tmp_path, AVX2), measure=None)
    assert (tmp_path / "xdg" / "drivingscene" / CACHE_NAME).exists()


# --- forcing and the callers -------------------------------------------------------------------


def test_forcing_wins(machine, monkeypatch):
    machine(NO_BF16)
    assert resolve_amp(None, "cpu") is False
    assert resolve_amp(True, "cpu") is True and resolve_amp(False, "cpu") is False
    machine(NATIVE)
    assert resolve_amp(None, torch.device("cpu")) is True and resolve_amp(False, "cpu") is False
    monkeypatch.setenv(ENV_VAR, "0")  # the environment forces where no flag is given
    assert resolve_amp(None, "cpu") is False and resolve_amp(True, "cpu") is True
    monkeypatch.setenv(ENV_VAR, "on")
    machine(NO_BF16)
    assert resolve_amp(None, "cpu") is True and resolve_amp(False, "cpu") is False
    monkeypatch.setenv(ENV_VAR, "auto")
    assert resolve_amp(None, "cpu") is False


def test_describe_precision(machine, monkeypatch):
    machine(NO_BF16)
    assert describe_precision("cpu") == "float32 (CPU AVX2, no native bf16)"
    assert describe_precision("cpu", True) == "bf16 autocast (forced; CPU AVX2, no native bf16)"
    machine(NATIVE)
    assert describe_precision("cpu") == "bf16 autocast (CPU AVX512 with AVX512_BF16)"
    assert describe_precision("cpu", False) == "float32 (forced; CPU AVX512 with AVX512_BF16)"
    monkeypatch.setenv(ENV_VAR, "0")
    assert describe_precision("cpu") == f"float32 ({ENV_VAR}; CPU AVX512 with AVX512_BF16)"


def test_inference_options_default_resolves_to_float32_without_native_bf16(machine, tmp_path):
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from tests.factories import make_pair

    machine(cpu_decision(cpuinfo(tmp_path, AVX2), tmp_path / "cache", Measure(), "AVX2", False))
    assert InferenceOptions().amp is None
    assert resolve_amp(InferenceOptions().amp, "cpu") is False
    recon = reconstruct(load_model(), make_pair(1, 24, 32), InferenceOptions(search=None))
    assert recon.meta["precision"] == "float32"


def test_inference_options_default_resolves_to_bf16_with_native_bf16(machine):
    from drivingscene.methods.feedforward import InferenceOptions

    machine(NATIVE)
    assert resolve_amp(InferenceOptions().amp, "cpu") is True
