"""``python -m torchbend.scenes CONFIG [options]``: run a scene config (see :mod:`torchbend.scenes.run`)."""
from .run import main

main()
