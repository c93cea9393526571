"""The HTTP API: the FastAPI application, its routes and bodies, and what guards them (connections,
rates, tenants, listeners, the body cap).  The application is :func:`yauyau.service.http.app.create_app`."""
