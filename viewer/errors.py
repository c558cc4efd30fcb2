"""User-facing errors: the CLI prints them as one line and exits non-zero."""


class RtwalkError(Exception):
    """An error caused by bad input or a missing facility (file, EGL, OpenCL).

    The message must be a single line that names the offending file or setting.
    """
