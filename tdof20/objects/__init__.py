"""TDoF20's 20 object classes: procedural watertight meshes in millimetres."""

from tdof20.objects.catalog import (
    ObjectModel,
    all_objects,
    export_models,
    get_object,
    object_by_name,
    object_id_by_name,
    object_ids,
    object_names,
)

__all__ = ["ObjectModel", "all_objects", "export_models", "get_object", "object_by_name", "object_id_by_name",
           "object_ids", "object_names"]
