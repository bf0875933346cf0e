"""The two ways the client fails."""


class SetupError(Exception):
    """Missing bindings, plugin, input or a bad argument: a usage problem, not a pipeline failure."""


class PipelineError(Exception):
    """An ERROR message from the pipeline (element name, message and debug text), or a stream
    the client cannot use."""
