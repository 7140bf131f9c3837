"""Developer tools: benchmarks, checks, previews and parameter studies, kept apart from the model.

Each is a command; nothing in vkgrl_newton outside tools/ imports them (the one exception is the
vkgrl_newton.gpu_check forwarder). A tool may import anything in the package.

    python -m vkgrl_newton.tools.gpu_check        every check that needs a GPU, one JSON report
                                                  (also `python -m vkgrl_newton.gpu_check`)
    python -m vkgrl_newton.tools.bench_kernels    Warp kernel microbenchmarks vs torch (`make bench`)
    python -m vkgrl_newton.tools.bench_sac        SAC gradient steps per second, ours vs stable-baselines3
    python -m vkgrl_newton.tools.bench_vision     render + encode cost per control step
    python -m vkgrl_newton.tools.throughput       env steps per second by world count, eager vs graph
    python -m vkgrl_newton.tools.contact_peaks    peak contact / constraint rows per task (nconmax, njmax)
    python -m vkgrl_newton.tools.preview          the task camera of a few worlds, tiled into one PNG
    python -m vkgrl_newton.tools.parts            the task parts alone: does the contact geometry work
    python -m vkgrl_newton.tools.kmp_param_study  the numbers behind the KMP defaults (lam, beta, l)
    python -m vkgrl_newton.tools.ceiling          privileged and blind controllers on the paired episodes, each loss classified

Importing this package loads nothing (`--help` of a tool answers without loading more than it must).
"""
