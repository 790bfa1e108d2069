"""Environment construction: MuJoCo's harmless deprecation notice never reaches the user."""

import io

from tests.procs import python_c
from tpdeb.services.envs import mujoco_warning


def test_mujoco_deprecation_notice_is_silenced_at_its_source():
    code = ("from tpdeb.services.envs import make_vector_env; "
            "make_vector_env('HalfCheetah-v5', 2).close(); print('built')")
    out = python_c(code)
    assert out.stdout.strip() == "built"
    assert "settotalmass" not in out.stderr and "WARNING" not in out.stderr, out.stderr


def test_other_mujoco_warnings_are_still_shown():
    shown = io.StringIO()
    mujoco_warning("compiler attribute 'settotalmass' is deprecated and will be removed", shown)
    mujoco_warning("Nan, Inf or huge value in QACC at DOF 0", shown)
    assert shown.getvalue() == "WARNING: Nan, Inf or huge value in QACC at DOF 0\n"
