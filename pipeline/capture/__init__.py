"""Working with a user's capture folder before the pipeline runs: creating one
with a documented capture.toml (``scaffold``) and checking its photos (``check``)."""
