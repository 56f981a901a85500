"""Episode store, catalog, video I/O, collection, training views, import and export."""
