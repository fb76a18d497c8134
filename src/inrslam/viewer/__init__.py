"""Browser viewer (viser, the optional extra `inrslam[viewer]`; docs/viewer.md).

- `shapes`: trajectory segments, frustum poses, colours (pure numpy);
- `content`: what is shown of one run directory (`RunContent`, from a `LoadedRun`);
- `tables`: metrics as markdown, one run or a comparison;
- `server`: the scene and panel of finished runs (`serve`, behind `inrslam view`);
- `live`: the progress callback that shows a running SLAM loop (`LiveViewer`, behind `inrslam run --viewer`).

Only `server` and `live` need viser, and import it when a server starts.
"""
