"""``python -m torchbend.scenes CONFIG [options]``: run a scene config (see :mod:`torchbend.scenes.run`)."""
from .cli import run_main
from .run import main

run_main(main, "python -m torchbend.scenes")
