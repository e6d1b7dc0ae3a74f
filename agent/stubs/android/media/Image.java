package android.media;

import java.nio.ByteBuffer;

public abstract class Image implements AutoCloseable {
    protected Image() {
        throw new RuntimeException("Stub!");
    }

    public abstract long getTimestamp();

    public abstract Plane[] getPlanes();

    public abstract void close();

    public abstract static class Plane {
        protected Plane() {
            throw new RuntimeException("Stub!");
        }

        public abstract ByteBuffer getBuffer();
    }
}
