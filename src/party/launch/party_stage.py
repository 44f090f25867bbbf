"""Re-entry point of a ``party <stage>`` in a child process.

Lightning's DDP launcher starts each extra local rank as ``python <sys.argv[0]>
<sys.argv[1:]>``; ``party.cli`` sets ``sys.argv[0]`` to this file and
``$PARTY_STAGE`` to the stage, so a child runs the same stage with the same
overrides (plus the Hydra run dir Lightning adds). This folder holds nothing
else, so running the file does not put other modules on ``sys.path``.
"""
import os
import sys

from party.cli import STAGE_ENV, run_stage

if __name__ == "__main__":
    run_stage(os.environ[STAGE_ENV], sys.argv[1:])
