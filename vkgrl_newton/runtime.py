"""Where things run, chosen in one place: the default device, the torch device of a Warp
device, and how loud Warp is. The sim, the env and every CLI use these. Warp and torch are
imported where used: `parse_cli` answers --help and argument errors before loading them."""

from __future__ import annotations

import sys

from .cli_types import add_verbose_flag, stderr_without  # noqa: F401  (add_verbose_flag: a name of this module too)

__all__ = ["default_device", "torch_device", "configure_warp", "add_verbose_flag", "parse_cli", "device_error",
           "cpu_model", "processor_name"]

# what Warp's native init prints on a machine without a GPU; nothing a CPU run can act on
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo's first 'model name'; platform's where there is none): what
    every speed figure and the CPU matmul choice (agents/matmul_backend.py) name their machine by."""
    import platform

    # (no /proc/cpuinfo, not Linux: platform's name)
    return _cpuinfo_fields("model name").get("model name") or platform.processor() or platform.machine() or "unknown"


def processor_name(device: str = "cpu") -> str:
    """The processor that runs `device`'s kernels: for "cpu" the CPU's model name with its family and model
    numbers (a cloud machine's model name is masked: "AMD EPYC" names a Zen 3 and a Zen 4 alike, whose instruction
    sets, and so Warp's `-march=native` kernels, differ), the GPU's name for a CUDA device. Results name it, and
    cached evaluations key on it, because float32 results differ between CPU models and tip chaotic contact
    outcomes: the same episodes seat differently on an Intel and an AMD CPU (docs/results/intel_prior_40), so an
    evaluation made on one machine is not another's."""
    if str(device).startswith("cuda"):
        import warp as wp

        return wp.get_device(str(device)).name
    numbers = _cpuinfo_fields("cpu family", "model")
    if len(numbers) < 2:  # no /proc/cpuinfo (not Linux) or no numbers there: the name alone
        return cpu_model()
    return f"{cpu_model()} (family {numbers['cpu family']} model {numbers['model']})"


def _cpuinfo_fields(*names: str, path: str = "/proc/cpuinfo") -> dict[str, str]:
    """The first value of each of `names` in /proc/cpuinfo ({} where there is no such file)."""
    try:
        with open(path) as f:
            lines = f.readlines()
    except OSError:
        return {}
    out: dict[str, str] = {}
    for line in lines:
        name, _, value = line.partition(":")
        if name.strip() in names and name.strip() not in out:
            out[name.strip()] = value.strip()
    return out


def default_device() -> str:
    """'cuda:0' when Warp sees a CUDA device, else 'cpu'. Warp decides, not torch: the physics
    runs in Warp, and the torch device follows from it (`torch_device`)."""
    import warp as wp

    return "cuda:0" if wp.is_cuda_available() else "cpu"


def device_error(device: str, flag: str = "--device") -> str | None:
    """Why `device` (cpu, cuda, cuda:N) cannot be used on this machine, naming the devices Warp
    can use here, or None. Call it before building anything, after `configure_warp`."""
    import warp as wp

    here = ["cpu"] + [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]
    if device == "cpu" or device in here or (device == "cuda" and len(here) > 1):
        return None
    if not device.startswith("cuda"):
        return f"{flag} {device!r} is not a device; allowed: cpu, cuda, cuda:N"
    why = "Warp sees no CUDA device on this machine" if len(here) == 1 else f"Warp sees {len(here) - 1} CUDA device(s)"
    return f"{flag} {device}: {why}; allowed here: {', '.join(here)}"


def torch_device(warp_device) -> torch.device:
    """The torch device sharing memory with a Warp device ('cuda:1' -> cuda:1, 'cpu' -> cpu)."""
    import warp as wp

    return wp.device_to_torch(wp.get_device(warp_device))


def configure_warp(verbose: bool = False) -> None:
    """Warp's messages off unless `verbose`: no banner, no per-module 'load ... (cached)' line, no
    missing-driver warning on a CPU machine; warnings and errors still show. Call it before
    Warp is first used (the CLIs do, first thing); later calls only change the log level."""
    import warp as wp

    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_WARNING
    if verbose or wp._src.context.runtime is not None:
        wp.init()
        return
    # the native init writes the driver warning to fd 2 itself: drop it there, pass the rest on
    with stderr_without(_NO_DRIVER):
        wp.init()


def parse_cli(parser, argv=None, device: bool = False):
    """Parse a CLI's arguments with `--verbose` added, set Warp's loudness from it, and, with
    `device`, resolve `--device` (None: `default_device()`) and say once which device it runs on."""
    add_verbose_flag(parser)
    args = parser.parse_args(argv)
    configure_warp(args.verbose)
    if device:
        args.device = args.device or default_device()
        if (why := device_error(args.device)) is not None:
            parser.error(why)
        print(f"{parser.prog}: device {args.device}", file=sys.stderr)
    return args
