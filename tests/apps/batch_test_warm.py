"""A module a test job's ``warm_up`` imports: importing it records the importing process's id in
``$TACSPLAT_TEST_WARM_DIR/imported``."""

import os
from pathlib import Path

Path(os.environ["TACSPLAT_TEST_WARM_DIR"], "imported").write_text(str(os.getpid()))
