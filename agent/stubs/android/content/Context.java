package android.content;

public abstract class Context {
    public static final String ACTIVITY_SERVICE = "activity";
    public static final String CAMERA_SERVICE = "camera";

    public Context() {
        throw new RuntimeException("Stub!");
    }

    public abstract String getPackageName();

    public abstract Context getApplicationContext();

    public abstract Object getSystemService(String name);

    public String getOpPackageName() {
        throw new RuntimeException("Stub!");
    }

    public AttributionSource getAttributionSource() {
        throw new RuntimeException("Stub!");
    }
}
