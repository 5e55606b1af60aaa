"""A training run as it is configured and stored, shared by the trainer (which writes it) and by bench, predict and
the viewer (which read it): ``config`` (every frozen config of a run and its JSON form), ``checkpoint`` (network
weights in the run folder and loading a trained network), ``folder`` (the run folder's record and resume rule),
``devices`` (the compute device, checked before work starts).
"""

__all__ = ["checkpoint", "config", "devices", "folder"]
