"""The core: pure logic (geometry, the domain model, the object-type grammar, filters, errors,
addresses, backoff). It imports nothing above it (docs/architecture.md, Layers)."""
