"""The topics of the stream: a sensor's keys are ``<prefix>/<sensor>/<topic>``. The one
list of them, shared by the wire formats (a message per topic) and the bus (the key
expressions), so that neither imports the other."""

#: the topics of a sensor's keys ``<prefix>/<sensor>/<topic>``
TOPICS = ("raw", "quantized", "targets", "tracks", "health")
#: the topics a recording adds beside a sensor's (replay.derived: never on the bus)
DERIVED_TOPICS = ("pointcloud", "scene", "profile")
