"""Dataset readers: the native folder format, YCB-Video, RBO, TUM RGB-D and ROS / RealSense bags."""

from artclass_core import hookimpl

from .bag import BagReader
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
    register(BagReader)
