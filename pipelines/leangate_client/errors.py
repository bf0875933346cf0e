"""How the client fails: two ways for a run (SetupError, PipelineError) and one for a call made
at the wrong time (NotRunningError)."""


class SetupError(Exception):
    """Missing bindings, plugin, input or a bad argument: a usage problem, not a pipeline failure."""


class PipelineError(Exception):
    """An ERROR message from the pipeline (element name, message and debug text), or a stream
    the client cannot use."""


class NotRunningError(RuntimeError):
    """A ``LeanGateSource`` call that needs its pipeline (``force_keyframe``, ``reset``,
    ``feedback``, iterating, ``start``) made before the source was started or after it was
    closed. ``state`` is ``"not started"`` or ``"closed"``; ``call`` names the method."""

    def __init__(self, call: str, state: str):
        self.call = call
        self.state = state
        if state == "closed":
            why = "the source is closed (a LeanGateSource runs its input once: make a new one)"
        else:
            why = (
                "the source is not started: there is no pipeline to send it to yet (call it "
                "while iterating, or after start() / entering the `with` block)"
            )
        super().__init__(f"{call}: {why}")
