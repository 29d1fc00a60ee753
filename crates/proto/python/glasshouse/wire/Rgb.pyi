from __future__ import annotations

import flatbuffers
import numpy as np

import typing

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class Rgb(object):
  @classmethod
  def SizeOf(cls) -> int: ...

  def Init(self, buf: bytes, pos: int) -> None: ...
  def R(self) -> int: ...
  def G(self) -> int: ...
  def B(self) -> int: ...

def CreateRgb(builder: flatbuffers.Builder, r: int, g: int, b: int) -> uoffset: ...

