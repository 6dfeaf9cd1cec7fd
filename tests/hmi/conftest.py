from __future__ import annotations

from collections.abc import Iterator

import pytest

from softplc.core.image import ImageSizes
from softplc.hmi.server import ModbusSlave
from tests.hmi.helpers import ImageSource, SlaveThread, run_in_thread


@pytest.fixture
def source() -> ImageSource:
    src = ImageSource(ImageSizes())
    img = src.image
    img.qx[[0, 3, 799]] = True
    img.mx[[1, 799]] = True
    img.ix[[2, 15, 799]] = True
    img.iw[:] = range(1024)
    img.qw[:] = [1000 + i for i in range(1024)]
    img.mw[:] = [(5000 + i) & 0xFFFF for i in range(1024)]
    src.publish()
    return src


@pytest.fixture
def slave(source: ImageSource) -> Iterator[SlaveThread]:
    with run_in_thread(ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0)) as h:
        yield h
