"""HTTP only: the FastAPI app, its dependencies, auth, problem documents, schemas and one routes
module per resource. Routes validate, call the store or the scheduler, and return a schema."""
