"""Foxglove: the channels (defined once), the live WebSocket server, MCAP recordings.

Nothing here runs on the loop thread but `VizRing.put` (a struct copy) and the daemon's
between-ticks hook; everything that encodes or sends runs on the publisher's thread or the
SDK's. Computation (ddrt/core, ddrt/path) never imports this package. foxglove-sdk is an
optional extra (`pip install 'ddrt[foxglove]'`), imported only through `optional.foxglove()`.
"""
