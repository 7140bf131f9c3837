"""Moved to vkgrl_newton.tools.gpu_check (`python -m vkgrl_newton.tools.gpu_check`).

This forwarder keeps `python -m vkgrl_newton.gpu_check` and `from vkgrl_newton import gpu_check`
working: the same command, the same report. It is the one module outside tools/ that imports
tools/.
"""

from .tools.gpu_check import *  # noqa: F401,F403 - the tool's __all__: main, cli, CHECKS, TASKS, the checks
from .tools.gpu_check import CHECKS, cli, main  # noqa: F401 - named again: what the tests and callers use

if __name__ == "__main__":
    raise SystemExit(cli())
