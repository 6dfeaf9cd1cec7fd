"""Small programs for the why tests: each shows one reason a transition does or does not
fire, on a symbols file without drivers (no device is opened)."""

from __future__ import annotations

from pathlib import Path

from softplc.core.context import ScanContext
from softplc.core.image import ProcessImage
from softplc.core.net import CompiledNet
from softplc.program.compiler import compile_text

IO = """
symbols:
  a:     {address: "%IX0.0", type: bool}
  b:     {address: "%IX0.1", type: bool}
  level: {address: "%IW0", type: word}
  lamp:  {address: "%QX0.0", type: bool}
"""


def compile_net(tmp_path: Path, body: str) -> CompiledNet:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    text = f"program: t\nio_image: io.yaml\n{body}"
    return compile_text(text, str(tmp_path / "t.yaml"), tmp_path)


def context(net: CompiledNet, **values: int) -> ScanContext:
    image = ProcessImage(net.io.sizes)
    for name, value in values.items():
        image.set(net.io.symbols[name].address, value)
    locations = {s.name: (s.address.attr, s.address.index) for s in net.io.symbols.values()}
    return ScanContext(image, image.copy(), locations, frozenset())
