"""The 20-object catalog of transparent objects: procedural watertight meshes in millimetres."""

from tdof20.objects.catalog import (
    ObjectModel,
    all_objects,
    export_models,
    get_object,
    object_by_name,
    object_ids,
)

__all__ = ["ObjectModel", "all_objects", "export_models", "get_object", "object_by_name", "object_ids"]
