"""Dataset readers: the native folder format, YCB-Video, RBO and TUM RGB-D."""

from artclass_core import hookimpl

from .folder import FolderReader
from .rbo import RboReader
from .tum import TumReader
from .ycbv import YcbvReader


@hookimpl
def register_readers(register):
    register(FolderReader)
    register(YcbvReader)
    register(RboReader)
    register(TumReader)
