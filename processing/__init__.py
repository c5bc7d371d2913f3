"""Processing: video motion magnification of every view, streamed in bounded memory."""
