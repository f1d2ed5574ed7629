"""Stream an unmodified X11 application: a private Xvfb screen (``display``), the
program on it (``app``), its pixels (``capture``) and its input through XTest
(``inject``). Needs Debian's ``xvfb`` and the extra ``game`` (mss, python-xlib)."""
