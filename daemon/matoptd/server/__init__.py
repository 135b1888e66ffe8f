"""The API's edge, in the server process: gRPC handlers, protobuf <-> plain data, who is calling,
and what a request may ask for before any worker sees it. Nothing here imports Mitsuba."""
