"""Dataset readers: the native folder format, YCB-Video, RBO and TUM RGB-D."""

from artclass_core import hookimpl

from .folder import FolderReader


@hookimpl
def register_readers(register):
    register(FolderReader)
