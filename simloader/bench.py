"""The older name of `simloader.tools.bench`, kept because the scripts in benchmarks/ import it
(`from simloader import bench`); it is that very module, so patching either patches both."""
import sys

from simloader.tools import bench as _bench

sys.modules[__name__] = _bench
