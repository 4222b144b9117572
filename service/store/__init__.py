"""The storage layer both processes share (API and workers): database engine and models, migrations,
blob stores, and the named transitions of tiles and fusion jobs. Knows nothing of HTTP."""
