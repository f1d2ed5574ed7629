"""The streaming session: ring U -> encoder -> moq-lite broadcast, inputs back to the game."""
