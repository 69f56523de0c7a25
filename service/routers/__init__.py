"""One APIRouter per resource: health, grids, sh, maps, shade, lights."""
