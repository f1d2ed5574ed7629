"""``upcast bench adaptive``: adaptive quality against fixed settings, and the picture
its viewers saw against the game's ground truth."""
