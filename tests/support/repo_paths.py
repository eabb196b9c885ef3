"""Where the repository and the tests' data files are."""

from pathlib import Path

#: The repository's root folder.
REPO_ROOT = Path(__file__).resolve().parents[2]
#: tests/data: the paper's tables and other fixed inputs.
TEST_DATA = REPO_ROOT / "tests" / "data"
#: Real ifm O3R captures (ifm3d's test data, copied with its NOTICE.md): held by the repository.
O3R_DATA = TEST_DATA / "o3r"
#: Real Luxonis OAK depth frames (copied with their NOTICE.md): held by the repository.
OAK_DATA = TEST_DATA / "real" / "oak"
