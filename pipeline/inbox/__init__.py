"""Scheduled offline reconstruction: the inbox watcher and its ledger. Imports: pipeline.jobs, pipeline.stores, pipeline.compute."""
