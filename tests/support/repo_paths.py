"""Where the repository and the tests' data files are."""

from pathlib import Path

#: The repository's root folder.
REPO_ROOT = Path(__file__).resolve().parents[2]
#: tests/data: the paper's tables and other fixed inputs.
TEST_DATA = REPO_ROOT / "tests" / "data"
