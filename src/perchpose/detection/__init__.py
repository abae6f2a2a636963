"""Finding the target's markers in a frame: ``detector.MarkerDetector`` puts the passes together
(the search, tracking in windows, the rectified pass); OpenCV's quads over every dictionary of
the target (``quads``), where to look (``windows``), a marker read back through its fitted
corners (``verification``) and the pinhole view of a distorted image (``rectification``)."""
