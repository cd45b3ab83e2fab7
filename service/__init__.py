"""The edge: command line now; FastAPI service, database and web pages later."""
