"""GPU memory as the driver tells it, and null where it does not."""

from __future__ import annotations

import pytest

from client.gpu_memory import NVX_EXTENSION, gl_integer, gpu_memory
from client.renderer import Renderer

GL_MAX_TEXTURE_SIZE = 0x0D33


def test_the_driver_query_reaches_the_renderers_context():
    with Renderer(64, 64, fov_y=60.0) as r:
        assert gl_integer(GL_MAX_TEXTURE_SIZE) == r.ctx.info["GL_MAX_TEXTURE_SIZE"] > 0


def test_a_driver_without_the_extension_gives_null_not_a_guess():
    with Renderer(64, 64, fov_y=60.0) as r:
        if NVX_EXTENSION in r.ctx.extensions:  # a GPU that tells: then the figure must be a real one
            used = gpu_memory(r.ctx.extensions)
            assert used is not None and used > 0
        else:
            assert gpu_memory(r.ctx.extensions) is None


@pytest.mark.parametrize("total, available, used", [
    (8 << 20, 6 << 20, (2 << 20) * 1024),  # 8 GiB board, 6 GiB free: 2 GiB in use
    (8 << 20, 8 << 20, 0),
    (0, 0, None),  # no total: nothing known
    (4 << 20, 5 << 20, None),  # more available than there is: nonsense
])
def test_nvx_figures_become_bytes_in_use(total, available, used):
    answers = {0x9048: total, 0x9049: available}
    assert gpu_memory({NVX_EXTENSION}, answers.__getitem__) == used


def test_a_query_that_cannot_load_gives_null():
    def broken(name: int) -> int:
        raise OSError("no libOpenGL")
    assert gpu_memory({NVX_EXTENSION}, broken) is None
