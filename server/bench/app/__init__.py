"""``upcast bench app`` and ``upcast bench capture``: real programs streamed as source
x11, and the X screen grabbers they are read with."""
