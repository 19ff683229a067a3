"""The rerun view shared by the viewer service and the offline converter: the message -> rerun mapping, its
geometry, and the stream with its layout."""
