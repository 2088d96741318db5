"""open3d is imported without its plotly/dash drawing helpers, which still work when called
(sparseart.geometry.o3d). Each case runs in a fresh interpreter: the import happens once per process."""
from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("open3d")


def _run(code: str) -> str:
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_open3d_loads_without_dash_and_its_plotly_helpers_still_run():
    out = _run(
        "import sys\n"
        "from sparseart.geometry.o3d import open3d\n"
        "o3d = open3d()\n"
        "print('dash' in sys.modules, 'plotly' in sys.modules)\n"
        "import numpy as np\n"
        "cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random((20, 3))))\n"
        "try:\n"
        "    import plotly\n"
        "except ImportError:\n"
        "    print('no plotly'); raise SystemExit\n"
        "figure = o3d.visualization.get_plotly_fig([cloud])\n"
        "print(type(figure).__name__, 'dash' in sys.modules)\n"
        "print(callable(o3d.visualization.draw_plotly), o3d.visualization.draw_plotly.__module__)\n")
    lines = out.split("\n")
    assert lines[0] == "False False"        # the 0.9 s of plotly/dash/IPython were not imported
    if lines[1] != "no plotly":
        assert lines[1] == "Figure True"     # the real helper ran on first use
        # the function, not the submodule the import binds on the package
        assert lines[2] == "True open3d.visualization.draw_plotly"


def test_a_name_the_stand_in_lacks_loads_the_real_module():
    """An open3d that imports more names from draw_plotly than the stand-in defines gets the real
    module's (simulated: the stand-in defines only one of the three)."""
    out = _run(
        "import sys\n"
        "import sparseart.geometry.o3d as o\n"
        "o.PLOTLY_NAMES = ('get_plotly_fig',)\n"   # draw_plotly / draw_plotly_server missing
        "try:\n"
        "    import plotly, dash\n"
        "except ImportError:\n"
        "    print('no plotly'); raise SystemExit\n"
        "o3d = o.open3d()\n"
        "print(o3d.visualization.draw_plotly.__module__, o3d.geometry.PointCloud.__name__)\n")
    if out.split("\n")[0] != "no plotly":
        assert out.split("\n")[0] == "open3d.visualization.draw_plotly PointCloud"
