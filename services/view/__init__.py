"""The views: the geometry both viewers draw from our messages (`geometry`); the rerun view shared by the viewer
service and the offline converter (`rerun_map`, `rerun_stream`); the Foxglove scene shared by the foxglove service,
the recorder and `gpmppi replay --foxglove-scene` (`foxglove_scene`, `foxglove_log`)."""
