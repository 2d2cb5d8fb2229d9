"""Which precision the networks run in: bf16 autocast where the hardware does bf16 natively,
float32 everywhere else. Used by inference (``methods.feedforward``), training (``train``), the
benchmarks and the viewer; every ``amp`` option there is ``None`` = decided here, ``True`` /
``False`` = forced.

Why: on a CPU with native bf16 (AVX512_BF16 or AMX-BF16 on x86, BF16 on ARM) bf16 autocast makes
the convolutions cheaper; on one without (e.g. an AVX2-only AMD EPYC) torch emulates bf16 and the
same networks run several times slower than in float32 (a 6x176x320 pair: 5.5-7.3 s against
1.5-1.8 s; one 3x3 convolution: ~60x).

The CPU decision, made once per machine (CPU model + flags + torch version) and cached:

1. Flags: the ``flags`` (x86) or ``Features`` (ARM) line of ``/proc/cpuinfo``. Native bf16 means
   ``avx512_bf16`` or ``amx_bf16`` (x86) or ``bf16`` (ARM). None of them: float32, no measurement.
   Where torch's oneDNN reports no bf16 support (``torch.ops.mkldnn._is_mkldnn_bf16_supported``)
   autocast would not reach native kernels either: float32. Without a readable cpuinfo (not
   Linux), oneDNN's report stands in for the flags (it also accepts plain AVX-512, where bf16 is
   emulated: the measurement below sorts that out).
2. Native bf16: confirmed by a measurement, one 3x3 convolution forward (2x32x96x176, as in the
   networks) in float32 and under bf16 autocast, best of 5 each after warm-up (well under 1 s;
   float32 ~4 ms on 2 AVX2 cores). bf16 is chosen unless it is slower than float32.
3. The decision is cached in ``$XDG_CACHE_HOME/drivingscene/precision.json`` (default
   ``~/.cache/drivingscene/``), one entry per key, written atomically. The file is never
   required: unreadable, corrupt or unwritable, the decision is simply made again.

On CUDA: bf16 autocast when ``torch.cuda.is_bf16_supported()``.

Forcing, strongest first: an explicit ``amp=True/False`` (``--amp`` / ``--no-amp``), then the
environment variable ``DRIVINGSCENE_AMP`` (``1``/``on`` or ``0``/``off``; ``auto`` or unset:
decide; for callers without a flag, e.g. the viewer), then the decision above.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import platform
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import torch

log = logging.getLogger(__name__)

CACHE_NAME = "precision.json"
CACHE_VERSION = 1
ENV_VAR = "DRIVINGSCENE_AMP"
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")  # x86 AVX-512 BF16, x86 AMX-BF16, ARM BF16
_ON = ("1", "on", "true", "yes", "bf16")
_OFF = ("0", "off", "false", "no", "fp32", "float32")

Measure = Callable[[], "tuple[float, float]"]


@dataclass(frozen=True)
class CpuPrecision:
    """The CPU decision and what it rests on."""

    bf16: bool  # bf16 autocast on this CPU
    native: tuple[str, ...]  # native bf16 flags found (empty: none)
    capability: str  # torch's CPU capability (AVX2, AVX512, ...)
    reason: str  # one phrase: why
    float32_ms: float | None = None  # the measurement, when one was made
    bf16_ms: float | None = None

    def cpu_words(self) -> str:
        """E.g. ``CPU AVX2, no native bf16`` / ``CPU AVX512 with AVX512_BF16, AMX_BF16``."""
        if not self.native:
            return f"CPU {self.capability}, no native bf16"
        return f"CPU {self.capability} with {', '.join(f.upper() for f in self.native)}"

    def describe(self) -> str:
        text = f"{'bf16 autocast' if self.bf16 else 'float32'} ({self.cpu_words()}"
        if self.float32_ms is not None and self.bf16_ms is not None:
            text += f"; 3x3 conv {self.bf16_ms:.1f} ms bf16 / {self.float32_ms:.1f} ms float32"
        return text + ")"


# ---------------------------------------------------------------------------------------------
# What the CPU is


def _cpuinfo_fields(path: str | os.PathLike = "/proc/cpuinfo") -> dict[str, str]:
    """The fields of the first processor in ``path`` (lower-case keys); empty where unreadable."""
    out: dict[str, str] = {}
    try:
        with open(path) as f:
            for line in f:
                if not line.strip():
                    if out:
                        break
                    continue
                key, _, value = line.partition(":")
                out.setdefault(key.strip().lower(), value.strip())
    except OSError:
        pass
    return out


def read_cpuinfo(path: str | os.PathLike = "/proc/cpuinfo") -> tuple[str, frozenset[str] | None]:
    """(model name, flags) of the first processor in ``path``; flags None where unreadable."""
    fields = _cpuinfo_fields(path)
    model = fields.get("model name") or fields.get("cpu model") or platform.processor() or platform.machine()
    flags = fields.get("flags", fields.get("features"))
    return model or "unknown CPU", None if flags is None else frozenset(flags.split())


SUMMARY_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_tile", "amx_bf16", "asimd", "sve", "bf16")


def cpu_flags_summary(path: str | os.PathLike = "/proc/cpuinfo") -> str:
    """The CPU's family and the vector flags that matter here, e.g. ``CPU family 25, flags AVX2
    FMA (no AVX-512, no native bf16)``, for benchmark reports."""
    fields = _cpuinfo_fields(path)
    _, flags = read_cpuinfo(path)
    family = f"CPU family {fields['cpu family']}" if "cpu family" in fields else "CPU"
    if flags is None:
        return f"{family}, flags unknown (torch CPU capability {torch_capability()})"
    found = [f.upper() for f in SUMMARY_FLAGS if f in flags]
    missing = [] if "avx512f" in flags or "asimd" in flags else ["no AVX-512"]
    missing += [] if native_bf16_flags(flags) else ["no native bf16"]
    return f"{family}, flags {' '.join(found) or 'none of AVX2/AVX-512'}" + (f" ({', '.join(missing)})" if missing else "")


def torch_capability() -> str:
    try:
        return str(torch.backends.cpu.get_cpu_capability())
    except Exception:  # older torch
        return "unknown"


def mkldnn_bf16() -> bool | None:
    """oneDNN's own bf16 check (None where torch has no oneDNN or no such check)."""
    try:
        if not torch.backends.mkldnn.is_available():
            return False
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except Exception:
        return None


def native_bf16_flags(flags: frozenset[str] | set[str]) -> tuple[str, ...]:
    return tuple(f for f in NATIVE_BF16_FLAGS if f in flags)


def measure_conv(repeats: int = 5) -> tuple[float, float]:
    """Best seconds of one 3x3 convolution forward in float32 and under bf16 autocast."""
    conv = torch.nn.Conv2d(32, 32, 3, padding=1).eval()
    x = torch.randn(2, 32, 96, 176)

    def once(bf16: bool) -> float:
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            tic = time.perf_counter()
            conv(x)
            return time.perf_counter() - tic

    for bf16 in (False, True, False, True):  # oneDNN builds its kernels on the first calls
        once(bf16)
    times = {False: [], True: []}
    for _ in range(repeats):  # alternating, so a slow spell falls on both
        for bf16 in (False, True):
            times[bf16].append(once(bf16))
    return min(times[False]), min(times[True])


def decide(
    flags: frozenset[str] | set[str] | None,
    capability: str | None = None,
    onednn_bf16: bool | None = None,
    measure: Measure | None = measure_conv,
) -> CpuPrecision:
    """The decision from the CPU's flags (None: unknown), torch's capability and oneDNN's bf16
    check, confirmed by ``measure() -> (float32 s, bf16 s)`` where bf16 looks native
    (``measure=None``: trust the flags). Nothing cached here."""
    capability = capability if capability is not None else torch_capability()
    if flags is None:
        native: tuple[str, ...] = ("onednn_bf16",) if onednn_bf16 else ()
    else:
        native = native_bf16_flags(flags)
    if not native:
        return CpuPrecision(False, (), capability, "no native bf16")
    if onednn_bf16 is False:
        return CpuPrecision(False, native, capability, "torch's oneDNN has no bf16 support here")
    if measure is None:
        return CpuPrecision(True, native, capability, "native bf16 (not measured)")
    try:
        fp32_s, bf16_s = measure()
    except Exception as e:  # a broken bf16 path is a reason not to use it
        return CpuPrecision(False, native, capability, f"bf16 measurement failed: {e}")
    ms = dict(float32_ms=round(fp32_s * 1e3, 3), bf16_ms=round(bf16_s * 1e3, 3))
    if bf16_s > fp32_s:
        return CpuPrecision(False, native, capability, "native bf16, but measured slower than float32", **ms)
    return CpuPrecision(True, native, capability, "native bf16, measured faster than float32", **ms)


# ---------------------------------------------------------------------------------------------
# The cache


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "drivingscene"


def cache_key(model: str, flags: frozenset[str] | set[str] | None, torch_version: str | None = None) -> str:
    text = "|".join([model, " ".join(sorted(flags)) if flags is not None else "?", torch_version or torch.__version__])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _read_cache(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("version") != CACHE_VERSION or not isinstance(data.get("entries"), dict):
        return {}
    return data["entries"]


def _from_entry(entry) -> CpuPrecision | None:
    try:
        decision = CpuPrecision(
            bf16=entry["bf16"],
            native=tuple(entry["native"]),
            capability=entry["capability"],
            reason=entry["reason"],
            float32_ms=entry.get("float32_ms"),
            bf16_ms=entry.get("bf16_ms"),
        )
    except (KeyError, TypeError):
        return None
    ok = isinstance(decision.bf16, bool) and all(isinstance(f, str) for f in decision.native)
    return decision if ok and isinstance(decision.capability, str) and isinstance(decision.reason, str) else None


def _write_cache(path: Path, entries: dict) -> None:
    """Atomic (a temporary file beside it, then a rename); any failure is only logged."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                json.dump({"version": CACHE_VERSION, "entries": entries}, f, indent=1, sort_keys=True)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:
        log.debug("%s: precision decision not cached: %s", path, e)


def cpu_decision(
    cpuinfo: str | os.PathLike = "/proc/cpuinfo",
    directory: str | os.PathLike | None = None,
    measure: Measure | None = measure_conv,
    capability: str | None = None,
    onednn_bf16: bool | None = None,
) -> CpuPrecision:
    """The decision for the CPU described by ``cpuinfo``, from the cache in ``directory``
    (default `cache_dir`) when it holds this CPU's entry, else made (`decide`) and cached."""
    model, flags = read_cpuinfo(cpuinfo)
    key = cache_key(model, flags)
    path = Path(directory) if directory is not None else cache_dir()
    path = path / CACHE_NAME
    entries = _read_cache(path)
    cached = _from_entry(entries.get(key))
    if cached is not None:
        return cached
    if onednn_bf16 is None:
        onednn_bf16 = mkldnn_bf16()
    decision = decide(flags, capability, onednn_bf16, measure)
    entry = {**asdict(decision), "cpu": model, "torch": torch.__version__, "decided": time.strftime("%Y-%m-%dT%H:%M:%S")}
    _write_cache(path, {**_read_cache(path), key: entry})
    log.info("precision on this CPU (decided once, cached in %s): %s", path, decision.describe())
    return decision


@functools.lru_cache(maxsize=1)
def machine_cpu_decision() -> CpuPrecision:
    """This machine's decision, once per process (`cpu_decision` with the defaults)."""
    return cpu_decision()


# ---------------------------------------------------------------------------------------------
# For callers


def env_amp() -> bool | None:
    """``DRIVINGSCENE_AMP``: True, False, or None (unset, ``auto`` or not understood)."""
    value = os.environ.get(ENV_VAR, "").strip().lower()
    if value in _ON:
        return True
    if value in _OFF:
        return False
    if value not in ("", "auto"):
        log.warning("%s=%r: expected 1/on, 0/off or auto; deciding automatically", ENV_VAR, value)
    return None


def _device(device) -> torch.device:
    return device if isinstance(device, torch.device) else torch.device(device)


def auto_amp(device="cpu") -> bool:
    """Whether bf16 autocast is the fast choice on ``device`` (no forcing applied)."""
    device = _device(device)
    if device.type == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    if device.type == "cpu":
        return machine_cpu_decision().bf16
    return False


def resolve_amp(requested: bool | None, device="cpu") -> bool:
    """``requested`` when given (True/False: forced), else ``DRIVINGSCENE_AMP``, else `auto_amp`."""
    if requested is not None:
        return bool(requested)
    forced = env_amp()
    return forced if forced is not None else auto_amp(device)


def describe_precision(device="cpu", requested: bool | None = None) -> str:
    """One phrase for reports: what runs and why, e.g. ``float32 (CPU AVX2, no native bf16)``,
    ``bf16 autocast (CPU AVX512 with AVX512_BF16; ...)``, ``float32 (forced; CPU ...)``."""
    device = _device(device)
    amp = resolve_amp(requested, device)
    how = "forced; " if requested is not None else (f"{ENV_VAR}; " if env_amp() is not None else "")
    name = "bf16 autocast" if amp else "float32"
    if device.type == "cuda":
        ok = torch.cuda.is_available() and torch.cuda.is_bf16_supported()
        gpu = torch.cuda.get_device_name(device) if torch.cuda.is_available() else "GPU"
        return f"{name} ({how}{gpu}, {'bf16 supported' if ok else 'no bf16'})"
    if device.type != "cpu":
        return f"{name} ({how}{device.type})"
    cpu = machine_cpu_decision()
    if not how:
        return cpu.describe()
    return f"{name} ({how}{cpu.cpu_words()})"
