"""Looking at a field: camera paths and fly-through videos (:mod:`.paths`, :mod:`.video`) and the browser
viewer with live text queries (:mod:`.server`, ``langfield view``)."""
