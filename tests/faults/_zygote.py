"""A fork server for the kill -9 test: import the service once, then fork a fresh ``serve`` per restart.

Importing the service takes ~4 s on the shared 2-core CI box, so 20 cold restarts alone would take
the suite's whole time budget.  This process imports ``service.cli.main`` and the modules ``serve`` loads
(no database, socket or thread is opened before the fork), then for each ``spawn`` line on stdin forks a
child that runs exactly ``service.cli.main.main(["serve", "--config", FILE])`` - the code path of
``python -m service.cli serve --config FILE`` - and prints its pid.  The test SIGKILLs the child; the
zygote reaps it on ``reap PID``.  ``OPENBLAS_NUM_THREADS=1`` is set by the caller so no BLAS thread
pool exists at fork time.
"""

from __future__ import annotations

import os
import sys


def main() -> int:
    config = sys.argv[1]
    import service.cli.commands.serve
    import service.cli.main
    import service.http.app

    print("ready", flush=True)
    for line in sys.stdin:
        cmd, _, arg = line.strip().partition(" ")
        if cmd == "spawn":
            pid = os.fork()
            if pid == 0:
                os.setsid()
                code = 1
                try:
                    code = service.cli.main.main(["serve", "--config", config])
                finally:
                    os._exit(code)
            print(pid, flush=True)
        elif cmd == "reap":
            os.waitpid(int(arg), 0)
            print("reaped", flush=True)
        elif cmd == "quit":
            return 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
