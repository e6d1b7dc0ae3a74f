package android.media;

import android.os.Handler;
import android.view.Surface;

public class ImageReader implements AutoCloseable {
    protected ImageReader() {
        throw new RuntimeException("Stub!");
    }

    public static ImageReader newInstance(int width, int height, int format, int maxImages) {
        throw new RuntimeException("Stub!");
    }

    public Surface getSurface() {
        throw new RuntimeException("Stub!");
    }

    public Image acquireLatestImage() {
        throw new RuntimeException("Stub!");
    }

    public Image acquireNextImage() {
        throw new RuntimeException("Stub!");
    }

    public void setOnImageAvailableListener(OnImageAvailableListener listener, Handler handler) {
        throw new RuntimeException("Stub!");
    }

    public void close() {
        throw new RuntimeException("Stub!");
    }

    public interface OnImageAvailableListener {
        void onImageAvailable(ImageReader reader);
    }
}
