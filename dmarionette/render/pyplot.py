"""matplotlib's pyplot for writing pictures to files, without a display."""

from __future__ import annotations

__all__ = ["headless_pyplot"]


def headless_pyplot(what: str = "pictures"):
    """``matplotlib.pyplot`` with the non-interactive Agg backend selected (files only: no window, no
    display needed). Imported on call, so a module that draws loads matplotlib only when it draws.

    Raises:
        RuntimeError: matplotlib is missing; the message says what needs it (``what``) and which
            extra to install.
    """
    try:
        import matplotlib
    except ImportError:
        raise RuntimeError(f"{what} need matplotlib: pip install -e '.[viz]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
