"""``upcast serve``: many game sessions on one host, each in its own process, one relay."""
