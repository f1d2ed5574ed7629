"""Adaptive quality: what each session renders, upscales and predicts, chosen from
its measured stage times, the host's load and the scene (issue 43).

- ``figures``: the speed-against-error table the choice rests on, derived from
  ``upcast eval``'s reports (``python -m server.session.quality.figures``).
- ``model``: expected picture quality and stage times of a setting, learned online.
- ``scene``: the scene's motion class from the frames' cameras and cut flags.
- ``controller``: the sans-IO controller (measurements and ``now`` in, a decision
  and its reason out).
- ``adapter``: binds the controller to a live session.
"""
