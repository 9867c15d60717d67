"""Where the tests find the real data: $HUMOTION_DATA, else ../shared/data beside the repository.

Point HUMOTION_DATA at another spelling of that folder (a symlink, a mounted drive) to run the data
tests through it. The library resolves a collection's root (symlinks followed), so the tests
compare paths resolved on both sides.
"""

from humotion.data import default_data_dir

DATA = default_data_dir()
MOCAP = DATA / "mocap"
