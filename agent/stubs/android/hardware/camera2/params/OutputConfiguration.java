package android.hardware.camera2.params;

import android.view.Surface;

public final class OutputConfiguration {
    public OutputConfiguration(Surface surface) {
        throw new RuntimeException("Stub!");
    }
}
