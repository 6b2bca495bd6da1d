"""The scene: Gaussians, cameras, trajectories and the views of a command, the file formats
(`scene.io`) and the generated synthetic scenes."""
