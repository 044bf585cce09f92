"""Files: scene folders and their readers, the field's field.json, PLY, and preprocessing."""
