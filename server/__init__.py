"""The steelscan ground station: ingest, storage, jobs, REST and the dashboard."""
